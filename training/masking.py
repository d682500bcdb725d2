"""The MaskGIT training collator: batch windows, then corrupt and mask them (TrainingRecipe.masking).

"published" is the published GENIE models' training; "whole_frames" masks frames whole, as the challenge evaluates,
and is what every shipped sample-world recipe trains with.
"""
from typing import Optional

import torch
from torch.utils.data import get_worker_info

from training.action_streams import stack_streams, window_actions
from common.config import ConfigError
from genie.config import GenieConfig, TrainingRecipe
from genie.factorization import factorize_token_ids, unfactorize_token_ids
from genie.model import MaskGITBatch
from genie.sampling import cosine_schedule


def _uniform(low: float, high: float, size, generator) -> torch.Tensor:
    return low + (high - low) * torch.rand(size, generator=generator)


def _window_tokens(items, config: GenieConfig) -> torch.Tensor:
    """The items' windows (B, T, H, W) int64; clear errors for windows that do not fit the model."""
    labels_BTHW = torch.stack([torch.as_tensor(item["tokens"]) for item in items]).long()
    if labels_BTHW.shape[1:] != (config.T, config.H, config.W):
        raise ValueError(f"maskgit collator: windows are {tuple(labels_BTHW.shape[1:])} tokens but the model "
                         f"config expects (T, H, W) = ({config.T}, {config.H}, {config.W}); check window_size and "
                         f"the dataset's s")
    if labels_BTHW.min() < 0 or labels_BTHW.max() >= config.image_vocab_size:
        raise ValueError(f"maskgit collator: token ids must lie in [0, image_vocab_size={config.image_vocab_size}), "
                         f"got range [{int(labels_BTHW.min())}, {int(labels_BTHW.max())}]")
    return labels_BTHW


def _corrupt(x_BTHWF: torch.Tensor, max_corrupt_rate: float, V: int, generator):
    """Step 1 of both schemes: each factor of each token replaced by a random factor value with probability
    max_corrupt_rate * u, u ~ U(0, 1) once per batch. Returns (the corrupted factors, the random values drawn for
    every position, which the published scheme's later corruption reuses)."""
    random_BTHWF = torch.randint(0, V, x_BTHWF.shape, generator=generator)
    corrupt_rate = max_corrupt_rate * torch.rand((), generator=generator)
    corrupt = torch.rand(x_BTHWF.shape, generator=generator) < corrupt_rate
    return torch.where(corrupt, random_BTHWF, x_BTHWF), random_BTHWF


def _published_masks(x_BTHWF: torch.Tensor, random_BTHWF: torch.Tensor, config: GenieConfig,
                     non_mlm_ratio: float, generator):
    """Steps 2-3 of the published scheme -> (factors (B, T, H, W, F) corrupted further, mask (B, T, H, W) bool).

    2. with probability non_mlm_ratio (closer to autoregressive inference), frames from first_masked_frame ~
       U{num_prompt_frames, ..., T-1} on get extra corruption: a factor is kept with probability correct_rate, which
       starts at U(0.25, 1) and shrinks by a U(0.9, 1) factor per frame; otherwise first_masked_frame = 1;
    3. each frame >= first_masked_frame of each example masks each token with probability cosine_schedule(U(0, 1))
       (redrawn when the whole batch got no mask). Frame 0 is never masked.
    """
    B, T, H, W, F = x_BTHWF.shape
    if torch.rand((), generator=generator) < non_mlm_ratio:
        first_masked_frame = int(torch.randint(config.num_prompt_frames, T, (), generator=generator))
        # Later frames are corrupted more: at inference, errors compound over generated frames.
        num_later = T - first_masked_frame
        correct_rate_T = (_uniform(0.25, 1.0, (), generator)
                          * torch.cumprod(_uniform(0.9, 1.0, num_later, generator), 0))
        wrong = torch.rand(B, num_later, H, W, F, generator=generator) > correct_rate_T.view(1, -1, 1, 1, 1)
        x_BTHWF[:, first_masked_frame:] = torch.where(wrong, random_BTHWF[:, first_masked_frame:],
                                                      x_BTHWF[:, first_masked_frame:])
    else:
        first_masked_frame = 1

    mask = torch.zeros(0, dtype=torch.bool)
    while not mask.any():  # an unlucky draw can mask nothing, which gives no training signal
        mask_prob_BT11 = cosine_schedule(torch.rand(B, T - first_masked_frame, 1, 1, generator=generator))
        mask = torch.rand(B, T - first_masked_frame, H, W, generator=generator) < mask_prob_BT11
    mask_BTHW = torch.zeros(B, T, H, W, dtype=torch.bool)
    mask_BTHW[:, first_masked_frame:] = mask
    return x_BTHWF, mask_BTHW


def _whole_frame_masks(n: int, T: int, H: int, W: int, generator) -> torch.Tensor:
    """(n, T, H, W) bool: every 2nd or every 3rd frame fully masked (random per example), from a random start
    within the first period.

    Every masked frame then follows a clean one, as every target does in the challenge's evaluation, and with
    period 3 it follows two, so the model also learns from the change between the last two frames (whether a token
    has just stayed put), which the evaluation always shows it. Independent coin flips per frame give fewer such
    targets and train two-step predictions (a masked frame after a masked one) that the evaluation never asks for.
    """
    period_n1 = 2 + torch.randint(0, 2, (n, 1), generator=generator)
    first_n1 = (1 + (torch.rand(n, 1, generator=generator) * period_n1).long()).clamp(max=T - 1)
    t_1T = torch.arange(T).unsqueeze(0)
    masked_nT = (t_1T >= first_n1) & ((t_1T - first_n1) % period_n1 == 0)
    return masked_nT[:, :, None, None].expand(n, T, H, W)


def _time_reversed(labels_BTHW: torch.Tensor, actions_BTD: Optional[torch.Tensor], recipe: TrainingRecipe,
                   generator):
    """A share recipe.time_reverse_ratio of the windows (B, T, H, W) played backward, with their actions (B, T, D)
    (or None) to match: row t drives frame t -> t+1, so the reversed window's row t is the mirrored row T-2-t (its
    last row drives no frame of the window). Windows with a nonzero (or unknown) column outside the swaps stay."""
    B = labels_BTHW.shape[0]
    reverse_B = torch.rand(B, generator=generator) < recipe.time_reverse_ratio
    if actions_BTD is not None:
        columns = list(range(actions_BTD.shape[-1]))
        for a, b in recipe.time_reverse_swaps or []:
            columns[a], columns[b] = b, a
        fixed = [d for d, source in enumerate(columns) if source == d]
        if fixed:
            reverse_B &= ~(actions_BTD[..., fixed] != 0).any(dim=2).any(dim=1)
        mirrored_BTD = actions_BTD.flip(1).roll(-1, dims=1)[..., columns]
        actions_BTD = torch.where(reverse_B[:, None, None], mirrored_BTD, actions_BTD)
    return torch.where(reverse_B[:, None, None, None], labels_BTHW.flip(1), labels_BTHW), actions_BTD


def get_maskgit_collator(config: GenieConfig, recipe: Optional[TrainingRecipe] = None, seed=None):
    """Return collate_fn(items) -> MaskGITBatch.

    items: RawTokenDataset items (tokens (T, H, W) int64, actions: name -> (T, k)); the batch's actions are the
    streams the config's action inputs use (training/action_streams.py). labels are the clean tokens; input_ids are
    corrupted (`_corrupt`) and masked (config.mask_token_id where the model is to predict) by recipe.masking
    (recipe: genie.config.TrainingRecipe, None: the published one):
    "published": `_published_masks` (more corruption in later frames for some batches, then cosine-rate masks);
    "whole_frames": `_whole_frame_masks` (every 2nd or 3rd frame masked whole; the others keep step 1's light
    corruption only).

    seed: None draws from torch's global RNG (seeded per DataLoader worker and by accelerate's set_seed); an int
    uses a private generator, seeded with seed + worker id inside DataLoader workers, so results are reproducible.
    """
    recipe = recipe or TrainingRecipe()
    if recipe.time_reverse_ratio > 0:
        if config.num_latent_actions:
            raise ConfigError("time_reverse_ratio: latent actions label a transition, which has no mirror; train "
                              "a model with latent actions without time reversal")
        swapped = [i for pair in recipe.time_reverse_swaps or [] for i in pair]
        if swapped and max(swapped) >= config.action_dim:
            raise ConfigError(f"time_reverse_swaps {recipe.time_reverse_swaps}: the model has {config.action_dim} "
                              f"action columns (indices 0..{config.action_dim - 1})")
    generators = {}

    def generator():
        if seed is None:
            return None
        worker = get_worker_info()
        key = worker.id if worker is not None else 0
        if key not in generators:
            generators[key] = torch.Generator().manual_seed(seed + key)
        return generators[key]

    def collate_fn(items) -> MaskGITBatch:
        g = generator()
        T, H, W, F, V = config.T, config.H, config.W, config.num_factored_vocabs, config.factored_vocab_size
        labels_BTHW = _window_tokens(items, config)
        actions_BTD, latent_BT = window_actions(config, stack_streams([item.get("actions", {}) for item in items]))
        if recipe.time_reverse_ratio > 0:  # drawn only then, so other recipes keep their masks
            labels_BTHW, actions_BTD = _time_reversed(labels_BTHW, actions_BTD, recipe, g)
        x_BTHWF, random_BTHWF = _corrupt(factorize_token_ids(labels_BTHW, F, V), recipe.max_corrupt_rate, V, g)
        if recipe.masking == "whole_frames":
            mask_BTHW = _whole_frame_masks(len(items), T, H, W, g)
        else:
            x_BTHWF, mask_BTHW = _published_masks(x_BTHWF, random_BTHWF, config, recipe.non_mlm_ratio, g)
        x_BTHW = unfactorize_token_ids(x_BTHWF, F, V)
        x_BTHW[mask_BTHW] = config.mask_token_id
        return MaskGITBatch(x_BTHW, labels_BTHW, actions_BTD, latent_BT)

    return collate_fn
