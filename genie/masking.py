"""MaskGIT training collator: batch windows, corrupt and mask them the way the published GENIE models were trained."""
from dataclasses import dataclass, fields
from typing import Optional

import torch
from torch.utils.data import get_worker_info

from genie.actions import stack_streams, window_actions
from genie.config import GenieConfig, TrainingRecipe
from genie.factorization import factorize_token_ids, unfactorize_token_ids
from genie.schedule import cosine_schedule


def _uniform(low: float, high: float, size, generator) -> torch.Tensor:
    return low + (high - low) * torch.rand(size, generator=generator)


def _whole_frame_masks(n: int, T: int, H: int, W: int, generator, clean_prefix_ratio: float,
                       max_first: int) -> torch.Tensor:
    """(n, T, H, W) bool: every 2nd or every 3rd frame fully masked (random per example), from a random start.

    Every masked frame then follows a clean one, as every target does in the challenge's evaluation, and with
    period 3 it follows two, so the model also learns from the change between the last two frames (whether a token
    has just stayed put), which the evaluation always shows it. Independent coin flips per frame give fewer such
    targets and train two-step predictions (a masked frame after a masked one) that the evaluation never asks for.

    The start lies within the first period, so no target follows more than 3 clean frames in a row. A share
    clean_prefix_ratio of the examples starts at U{1, ..., max_first} instead: its first target follows up to
    max_first whole frames, as a rollout's first generated frame follows its prompt.
    """
    period_n1 = 2 + torch.randint(0, 2, (n, 1), generator=generator)
    first_n1 = 1 + (torch.rand(n, 1, generator=generator) * period_n1).long()
    if clean_prefix_ratio > 0:  # drawn only when on, so the default's random stream is the published one
        prefixed_n1 = torch.rand(n, 1, generator=generator) < clean_prefix_ratio
        first_n1 = torch.where(prefixed_n1, torch.randint(1, max_first + 1, (n, 1), generator=generator), first_n1)
    first_n1 = first_n1.clamp(max=T - 1)
    t_1T = torch.arange(T).unsqueeze(0)
    masked_nT = (t_1T >= first_n1) & ((t_1T - first_n1) % period_n1 == 0)
    return masked_nT[:, :, None, None].expand(n, T, H, W)


def _two_stream_target_masks(B: int, T: int, H: int, W: int, partial_ratio: float, generator) -> torch.Tensor:
    """(B, T, H, W) bool: every frame >= 1 a target, whole (MaskGIT's first step) or, with probability
    partial_ratio, each token masked with a cosine-schedule rate (its later steps); frame 0 never masked."""
    rate_BT11 = cosine_schedule(torch.rand(B, T, 1, 1, generator=generator))
    partial_BT11 = torch.rand(B, T, 1, 1, generator=generator) < partial_ratio
    mask_BTHW = torch.rand(B, T, H, W, generator=generator) < torch.where(partial_BT11, rate_BT11, 1.0)
    empty_BT = ~mask_BTHW.flatten(2).any(-1)
    mask_BTHW[empty_BT] = True  # a target with nothing masked would give no signal: mask it whole instead
    mask_BTHW[:, 0] = False
    return mask_BTHW


def _context_noise(x_BTHWF: torch.Tensor, mask_BTHW: torch.Tensor, recipe: TrainingRecipe, V: int, generator):
    """Corrupt the context frames of a share recipe.context_noise_ratio of the examples (the collator's step 5):
    -> (factored tokens (B, T, H, W, F), levels (B, T) float, 0 for frame 0, wholly masked frames and the examples
    left clean)."""
    B, T = x_BTHWF.shape[:2]
    chosen_B1 = torch.rand(B, 1, generator=generator) < recipe.context_noise_ratio
    level_BT = recipe.context_noise_max * torch.rand(B, T, generator=generator) * chosen_B1
    level_BT[:, 0] = 0.0
    level_BT = level_BT.masked_fill(mask_BTHW.flatten(2).all(-1), 0.0)
    replace_BTHW = (torch.rand(mask_BTHW.shape, generator=generator) < level_BT[:, :, None, None]) & ~mask_BTHW
    random_BTHWF = torch.randint(0, V, x_BTHWF.shape, generator=generator)
    return torch.where(replace_BTHW.unsqueeze(-1), random_BTHWF, x_BTHWF), level_BT


def _jitter_speed(actions_BTD: torch.Tensor, recipe: TrainingRecipe, generator) -> torch.Tensor:
    """(B, T, D) actions with the columns recipe.speed_jitter_columns of each window scaled by one factor
    (1 + recipe.speed_jitter) ** U(-1, 1) (the collator's step 7); unknown (NaN) rows stay unknown."""
    B, _, D = actions_BTD.shape
    columns = recipe.speed_jitter_columns
    if max(columns) >= D:
        raise ValueError(f"maskgit collator: speed_jitter_columns {columns} name columns beyond the model's "
                         f"{D} action values")
    scale_B11 = (1.0 + recipe.speed_jitter) ** _uniform(-1.0, 1.0, (B, 1, 1), generator)
    scaled_BTD = actions_BTD.clone()
    scaled_BTD[..., columns] = actions_BTD[..., columns] * scale_B11
    return scaled_BTD


@dataclass
class MaskGITBatch:
    """A collated training batch; token ids are int64 (B, T, H, W)."""
    input_ids: torch.Tensor  # what the model sees: corrupted, the mask token where it is to predict
    labels: torch.Tensor  # the clean tokens
    target_ids: Optional[torch.Tensor] = None  # two-stream batches: every frame t >= 1 a (partly) masked target
    actions: Optional[torch.Tensor] = None  # (B, T, D) float: the config's real action streams
    latent_actions: Optional[torch.Tensor] = None  # (B, T) int64: latent action ids
    context_noise: Optional[torch.Tensor] = None  # (B, T) float: each frame's share of tokens made random

    def __post_init__(self):
        if self.input_ids.dim() != 4 or self.labels.shape != self.input_ids.shape:
            raise ValueError(f"MaskGITBatch: input_ids and labels must both be (B, T, H, W); got "
                             f"{tuple(self.input_ids.shape)} and {tuple(self.labels.shape)}")

    def to(self, device, non_blocking: bool = False) -> "MaskGITBatch":
        return MaskGITBatch(**{f.name: None if getattr(self, f.name) is None else
                               getattr(self, f.name).to(device, non_blocking=non_blocking) for f in fields(self)})


def get_maskgit_collator(config: GenieConfig, recipe: Optional[TrainingRecipe] = None, seed=None):
    """Return collate_fn(items) -> MaskGITBatch.

    items: RawTokenDataset items (tokens (T, H, W) int64, actions: name -> (T, k)); the batch's actions are the
    streams the config's action inputs use (genie/actions.py). labels are the clean tokens. input_ids are
    corrupted as in training of the published models (recipe: genie.config.TrainingRecipe, None: the published one):
    1. every factor of every token is replaced by a random factor value with probability max_corrupt_rate * u,
       u ~ U(0, 1) once per batch;
    2. with probability non_mlm_ratio (closer to autoregressive inference), frames from first_masked_frame ~
       U{num_prompt_frames, ..., T-1} on get extra corruption: a factor is kept with probability correct_rate, which
       starts at U(0.25, 1) and shrinks by a U(0.9, 1) factor per frame; otherwise first_masked_frame = 1;
    3. each frame >= first_masked_frame of each example masks each token with probability cosine_schedule(U(0, 1))
       (redrawn when the whole batch got no mask); masked tokens become config.mask_token_id. Frame 0 is never masked.
    4. opt-in (recipe.whole_frame_mask_ratio > 0, not in the published recipe): that fraction of the examples is
       instead masked the way the challenge evaluates: every 2nd or 3rd frame is fully masked (`_whole_frame_masks`),
       the others keep their tokens with step 1's light corruption only (not step 2's). Each masked frame is then
       predicted from whole earlier frames, nothing of itself revealed, which the published masking rarely shows a
       model (its frames are partly masked, and the frames before them too). recipe.clean_prefix_ratio of those
       examples keeps a clean prefix of up to num_prompt_frames frames before its first masked frame.
    5. opt-in (recipe.context_noise_ratio > 0): that fraction of the examples has each frame >= 1 that is not
       wholly masked corrupted at a level ~ U(0, recipe.context_noise_max) of its own: each unmasked token replaced
       by a uniformly random token with that probability (`_context_noise`); the levels go to the batch
       (context_noise, zero elsewhere), for a model that is told them (GenieConfig.context_noise_input).
    6. opt-in (recipe.two_stream_ratio > 0): that fraction of the batches is instead two-stream: input_ids are the
       whole windows with step 1's light corruption (the context) and target_ids holds every frame t >= 1 as a
       target, fully masked or, for recipe.two_stream_partial_ratio of them, partly (`_two_stream_target_masks`);
       genie/objectives.py predicts target t from context frames < t.

    7. opt-in (recipe.speed_jitter > 0), drawn last: each window's forward-speed action columns
       (recipe.speed_jitter_columns) are scaled by one factor (1 + speed_jitter) ** U(-1, 1) (`_jitter_speed`), so the
       model learns to read from the frames it has seen how far a step moves the view instead of trusting the
       speed's magnitude; the tokens and masks are those of the same batch without it.

    seed: None draws from torch's global RNG (seeded per DataLoader worker and by accelerate's set_seed); an int
    uses a private generator, seeded with seed + worker id inside DataLoader workers, so results are reproducible.
    """
    recipe = recipe or TrainingRecipe()
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
        batch = corrupt_and_mask(items)
        if recipe.speed_jitter > 0 and batch.actions is not None:
            # drawn after the masks, so jitter changes the actions and nothing else of the batch
            batch.actions = _jitter_speed(batch.actions, recipe, generator())
        return batch

    def corrupt_and_mask(items) -> MaskGITBatch:
        g = generator()
        T, H, W, F, V = config.T, config.H, config.W, config.num_factored_vocabs, config.factored_vocab_size
        labels_BTHW = torch.stack([torch.as_tensor(item["tokens"]) for item in items]).long()
        B = len(items)
        if labels_BTHW.shape[1:] != (T, H, W):
            raise ValueError(f"maskgit collator: windows are {tuple(labels_BTHW.shape[1:])} tokens but the model "
                             f"config expects (T, H, W) = ({T}, {H}, {W}); check window_size and the dataset's s")
        if labels_BTHW.min() < 0 or labels_BTHW.max() >= config.image_vocab_size:
            raise ValueError(f"maskgit collator: token ids must lie in [0, image_vocab_size="
                             f"{config.image_vocab_size}), got range [{int(labels_BTHW.min())}, "
                             f"{int(labels_BTHW.max())}]")
        actions_BTD, latent_BT = window_actions(config, stack_streams([item.get("actions", {}) for item in items]))
        x_BTHWF = factorize_token_ids(labels_BTHW, F, V)

        random_BTHWF = torch.randint(0, V, x_BTHWF.shape, generator=g)
        corrupt_rate = recipe.max_corrupt_rate * torch.rand((), generator=g)
        corrupt = torch.rand(x_BTHWF.shape, generator=g) < corrupt_rate
        x_BTHWF = torch.where(corrupt, random_BTHWF, x_BTHWF)
        if recipe.two_stream_ratio > 0 and torch.rand((), generator=g) < recipe.two_stream_ratio:
            context_BTHW = unfactorize_token_ids(x_BTHWF, F, V)
            targets_BTHW = context_BTHW.clone()
            targets_BTHW[_two_stream_target_masks(B, T, H, W, recipe.two_stream_partial_ratio, g)] = \
                config.mask_token_id
            return MaskGITBatch(context_BTHW, labels_BTHW, targets_BTHW, actions_BTD, latent_BT)
        lightly_corrupted_BTHWF = x_BTHWF.clone() if recipe.whole_frame_mask_ratio > 0 else None

        if torch.rand((), generator=g) < recipe.non_mlm_ratio:
            first_masked_frame = int(torch.randint(config.num_prompt_frames, T, (), generator=g))
            # Later frames are corrupted more: at inference, errors compound over generated frames.
            num_later = T - first_masked_frame
            correct_rate_T = _uniform(0.25, 1.0, (), g) * torch.cumprod(_uniform(0.9, 1.0, num_later, g), 0)
            wrong = torch.rand(B, num_later, H, W, F, generator=g) > correct_rate_T.view(1, -1, 1, 1, 1)
            x_BTHWF[:, first_masked_frame:] = torch.where(wrong, random_BTHWF[:, first_masked_frame:],
                                                          x_BTHWF[:, first_masked_frame:])
        else:
            first_masked_frame = 1

        mask = torch.zeros(0, dtype=torch.bool)
        while not mask.any():  # an unlucky draw can mask nothing, which gives no training signal
            mask_prob_BT11 = cosine_schedule(torch.rand(B, T - first_masked_frame, 1, 1, generator=g))
            mask = torch.rand(B, T - first_masked_frame, H, W, generator=g) < mask_prob_BT11

        mask_BTHW = torch.zeros(B, T, H, W, dtype=torch.bool)
        mask_BTHW[:, first_masked_frame:] = mask
        if lightly_corrupted_BTHWF is not None:
            forced_B = torch.rand(B, generator=g) < recipe.whole_frame_mask_ratio
            x_BTHWF[forced_B] = lightly_corrupted_BTHWF[forced_B]
            mask_BTHW[forced_B] = _whole_frame_masks(int(forced_B.sum()), T, H, W, g, recipe.clean_prefix_ratio,
                                                     config.num_prompt_frames)
        noise_BT = None
        if recipe.context_noise_ratio > 0:
            x_BTHWF, noise_BT = _context_noise(x_BTHWF, mask_BTHW, recipe, V, g)
        x_BTHW = unfactorize_token_ids(x_BTHWF, F, V)
        x_BTHW[mask_BTHW] = config.mask_token_id
        return MaskGITBatch(x_BTHW, labels_BTHW, None, actions_BTD, latent_BT, noise_BT)

    return collate_fn
