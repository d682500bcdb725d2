"""MaskGIT training collator: masking and corruption invariants, rates, determinism."""
import math

import numpy as np
import pytest
import torch

from data import RawTokenDataset, TokenDatasetError, write_token_dataset
from genie.config import GenieConfig, TrainingRecipe
from genie.factorization import factorize_token_ids
from training.masking import get_maskgit_collator
from genie.model import MaskGITBatch

T, S, VOCAB = 6, 16, 64  # 2 factors of 8
H = W = 4


def tiny_config(**overrides):
    fields = dict(num_layers=1, num_heads=1, d_model=8, T=T, S=S, image_vocab_size=VOCAB, num_prompt_frames=2)
    return GenieConfig(**{**fields, **overrides})


def action_config(**overrides):
    """A config whose model reads the 3-wide action stream "a" of make_features(actions=True)."""
    return tiny_config(action_names=["a"], action_dim=3, **overrides)


def make_features(batch_size, seed=0, actions=False, T=T):
    g = torch.Generator().manual_seed(seed)
    features = []
    for _ in range(batch_size):
        x = torch.randint(0, VOCAB, (T, H, W), generator=g)
        feature = {"tokens": x, "actions": {}}
        if actions:
            feature["actions"]["a"] = torch.randn(T, 3, generator=g)
        features.append(feature)
    return features


def frames(x):
    """(B, T, H, W) -> (B, T, S)"""
    return x.flatten(2)


@pytest.mark.parametrize("non_mlm_ratio", [0.0, 0.5, 1.0])
def test_invariants(non_mlm_ratio):
    config = tiny_config()
    collate = get_maskgit_collator(config, TrainingRecipe(non_mlm_ratio=non_mlm_ratio), seed=0)
    for i in range(30):
        features = make_features(4, seed=i)
        originals = torch.stack([f["tokens"] for f in features]).clone()
        batch = collate(features)
        assert isinstance(batch, MaskGITBatch)
        assert batch.actions is None and batch.latent_actions is None
        assert batch.input_ids.dtype == batch.labels.dtype == torch.int64
        assert batch.input_ids.shape == batch.labels.shape == (4, T, H, W)
        assert torch.equal(batch.labels, originals)
        assert torch.equal(torch.stack([f["tokens"] for f in features]), originals)  # features left intact
        x = frames(batch.input_ids)
        masked = x == config.mask_token_id
        assert masked.any()
        assert not masked[:, 0].any()
        assert ((x >= 0) & (x <= VOCAB)).all()
        if non_mlm_ratio == 1.0:
            assert not masked[:, :config.num_prompt_frames].any()


def test_without_corruption_only_masks_change():
    config = tiny_config()
    collate = get_maskgit_collator(config, TrainingRecipe(max_corrupt_rate=0.0, non_mlm_ratio=0.0), seed=1)
    masked_fraction = []
    for i in range(200):
        batch = collate(make_features(8, seed=i))
        x, labels = frames(batch.input_ids), frames(batch.labels)
        masked = x == config.mask_token_id
        assert torch.equal(x[~masked], labels[~masked])
        masked_fraction.append(masked[:, 1:].float().mean().item())
    # Per-frame mask probability cos(pi/2 u), u ~ U(0, 1), has mean 2/pi.
    assert abs(np.mean(masked_fraction) - 2 / math.pi) < 0.03


def test_random_corruption_rate():
    config = tiny_config()
    collate = get_maskgit_collator(config, TrainingRecipe(max_corrupt_rate=1.0, non_mlm_ratio=0.0), seed=2)
    changed = []
    for i in range(400):
        batch = collate(make_features(2, seed=i))
        # Frame 0 is never masked, so it shows the random corruption alone.
        f_in = factorize_token_ids(frames(batch.input_ids)[:, 0], 2, 8)
        f_label = factorize_token_ids(frames(batch.labels)[:, 0], 2, 8)
        changed.append((f_in != f_label).float().mean().item())
    # A factor is redrawn with probability u (u ~ U(0, 1) per batch) and lands on a new value with 7/8.
    assert abs(np.mean(changed) - 0.5 * 7 / 8) < 0.05


def test_autoregressive_corruption():
    config = tiny_config(T=8, num_prompt_frames=3)
    collate = get_maskgit_collator(config, TrainingRecipe(max_corrupt_rate=0.0, non_mlm_ratio=1.0), seed=3)
    first_frames, wrong_rate = [], []
    for i in range(100):
        g = torch.Generator().manual_seed(i)
        labels = torch.randint(0, VOCAB, (4, 8, S), generator=g)
        batch = collate([{"tokens": x.view(8, H, W), "actions": {}} for x in labels])
        x = batch.input_ids.view(4, 8, S)
        changed = (x != labels).any(dim=(0, 2))
        first = int(changed.float().argmax())
        first_frames.append(first)
        unmasked = x[:, first:] != config.mask_token_id
        wrong_rate.append((x[:, first:] != labels[:, first:])[unmasked].float().mean().item())
    assert min(first_frames) >= 3 and set(first_frames) == {3, 4, 5, 6, 7}
    # Factors are kept with probability correct_rate in [0.25 * 0.9^k, 1]: a sizeable but partial corruption.
    assert 0.2 < np.mean(wrong_rate) < 0.7


def test_deterministic_with_seed():
    config = tiny_config()
    outputs = [get_maskgit_collator(config, seed=seed)(make_features(3)) for seed in (5, 5, 6)]
    assert torch.equal(outputs[0].input_ids, outputs[1].input_ids)
    assert not torch.equal(outputs[0].input_ids, outputs[2].input_ids)
    torch.manual_seed(0)
    a = get_maskgit_collator(config)(make_features(3))
    torch.manual_seed(0)
    b = get_maskgit_collator(config)(make_features(3))
    assert torch.equal(a.input_ids, b.input_ids)


def test_actions_stacked():
    features = make_features(3, actions=True)
    batch = get_maskgit_collator(action_config(), seed=0)(features)
    assert batch.actions.shape == (3, T, 3) and batch.actions.dtype == torch.float32
    assert torch.equal(batch.actions[2], features[2]["actions"]["a"])
    assert batch.latent_actions is None
    # a video-only model gets no actions even when the windows have them
    assert get_maskgit_collator(tiny_config(), seed=0)(features).actions is None
    del features[1]["actions"]["a"]
    with pytest.raises(TokenDatasetError, match="a.bin"):
        get_maskgit_collator(action_config(), seed=0)(features)


def test_bad_windows_rejected():
    collate = get_maskgit_collator(tiny_config(), seed=0)
    with pytest.raises(ValueError, match="window_size"):
        collate([{"tokens": torch.zeros(T - 1, H, W, dtype=torch.long), "actions": {}}])
    with pytest.raises(ValueError, match="image_vocab_size"):
        collate([{"tokens": torch.full((T, H, W), VOCAB), "actions": {}}])


def test_with_dataset_and_dataloader(tmp_path):
    rng = np.random.default_rng(0)
    write_token_dataset(tmp_path, rng.integers(0, VOCAB, (40, 4, 4)), actions={"a": rng.normal(size=(40, 2))},
                        metadata={"vocab_size": VOCAB})
    ds = RawTokenDataset(tmp_path, window_size=T, stride=2)
    config = tiny_config(action_names=["a"], action_dim=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=5, collate_fn=get_maskgit_collator(config, seed=0))
    batch = next(iter(loader))
    assert batch.input_ids.shape == (5, T, H, W) and batch.actions.shape == (5, T, 2)
    assert torch.equal(batch.labels[3], ds[3]["tokens"])
    assert torch.equal(batch.actions[3], ds[3]["actions"]["a"])


@pytest.mark.parametrize("non_mlm_ratio", [0.0, 1.0])
def test_whole_frame_masking_masks_whole_frames_over_clean_context(non_mlm_ratio):
    config = tiny_config()
    recipe = TrainingRecipe(masking="whole_frames", max_corrupt_rate=0.0, non_mlm_ratio=non_mlm_ratio)
    collate = get_maskgit_collator(config, recipe, seed=0)
    first_targets = set()
    for step in range(20):
        batch = collate(make_features(4, seed=step))
        x, labels = frames(batch.input_ids), frames(batch.labels)
        masked = x == config.mask_token_id
        per_frame = masked.sum(-1)
        assert ((per_frame == 0) | (per_frame == S)).all(), "a frame is either fully masked or not at all"
        assert (per_frame[:, 0] == 0).all() and (per_frame[:, 1:] > 0).any(dim=1).all()
        whole = per_frame == S
        assert not (whole[:, 1:] & whole[:, :-1]).any(), "a masked frame always follows a clean one"
        assert (whole.sum(1) >= (config.T - 1) // 3).all(), "every 2nd or 3rd frame is a target"
        gaps = {int(g) for row in whole for g in torch.diff(torch.nonzero(row).flatten())}
        assert gaps <= {2, 3}
        first_targets |= set(whole.float().argmax(1).tolist())
        # kept frames are clean even when the batch drew the non-MLM corruption of later frames
        assert torch.equal(x[~masked], labels[~masked])
    assert first_targets == {1, 2, 3}  # every phase occurs


def test_whole_frame_masking_draws_only_what_it_uses():
    """The published scheme's later-frame corruption (non_mlm_ratio) plays no part in whole-frame masking, so the
    batches are the same whatever it is set to; the light corruption of step 1 still reaches the kept frames."""
    config = tiny_config()
    batches = [get_maskgit_collator(config, TrainingRecipe(masking="whole_frames", max_corrupt_rate=0.2,
                                                          non_mlm_ratio=r), seed=3)(make_features(8, seed=1))
               for r in (0.0, 1.0)]
    assert torch.equal(batches[0].input_ids, batches[1].input_ids)
    x, labels = frames(batches[0].input_ids), frames(batches[0].labels)
    kept = x != config.mask_token_id
    assert 0 < (x[kept] != labels[kept]).float().mean() < 1 - 0.8 ** 2  # each factor at most 20 %


def test_published_and_whole_frame_masking_differ_and_are_checked():
    config = tiny_config()
    published = get_maskgit_collator(config, TrainingRecipe(), seed=0)(make_features(8))
    per_frame = (frames(published.input_ids) == config.mask_token_id).sum(-1)
    assert ((per_frame > 0) & (per_frame < S)).any(), "published masks are partial"
    with pytest.raises(ValueError, match="masking must be one of"):
        TrainingRecipe(masking="whole_frame")


def _button_features(batch_size, seed=0):
    """Windows with a 3-wide stream "a" read as (forward, backward, use): each row holds forward or backward."""
    g = torch.Generator().manual_seed(seed)
    features = []
    for _ in range(batch_size):
        rows = torch.zeros(T, 3)
        rows[torch.arange(T), torch.randint(0, 2, (T,), generator=g)] = torch.rand(T, generator=g) + 0.1
        features.append({"tokens": torch.randint(0, VOCAB, (T, H, W), generator=g), "actions": {"a": rows}})
    return features


def test_time_reversal_plays_windows_backward_with_mirrored_actions():
    """A reversed window's frames run backward and its row t (which drives frame t -> t+1) is row T-2-t with
    forward and backward swapped; windows that hold a column outside the swaps (USE) are never reversed."""
    config = action_config()
    recipe = TrainingRecipe(masking="whole_frames", time_reverse_ratio=0.5, time_reverse_swaps=[[0, 1]])
    collate = get_maskgit_collator(config, recipe, seed=0)
    reversed_count = kept_count = 0
    for step in range(10):
        features = _button_features(8, seed=step)
        features[0]["actions"]["a"][3, 2] = 1.0  # USE held once: this window stays as it is
        batch = collate(features)
        for b, feature in enumerate(features):
            tokens, rows = feature["tokens"], feature["actions"]["a"]
            if torch.equal(batch.labels[b], tokens):
                assert torch.equal(batch.actions[b], rows)
                kept_count += 1
                continue
            assert b != 0
            assert torch.equal(batch.labels[b], tokens.flip(0))
            mirrored = rows[:, [1, 0, 2]]
            assert torch.equal(batch.actions[b, :T - 1], mirrored.flip(0)[1:])
            reversed_count += 1
    assert reversed_count > 20 and kept_count > 20  # about half of each


def test_time_reversal_off_keeps_the_masks_and_checks_its_settings():
    features = _button_features(8, seed=1)
    plain = get_maskgit_collator(action_config(), TrainingRecipe(masking="whole_frames"), seed=4)(features)
    zero = get_maskgit_collator(action_config(), TrainingRecipe(masking="whole_frames", time_reverse_ratio=0.0,
                                                                time_reverse_swaps=[[0, 1]]), seed=4)(features)
    assert torch.equal(plain.input_ids, zero.input_ids) and torch.equal(plain.actions, zero.actions)
    with pytest.raises(ValueError, match="time_reverse_swaps must be pairs"):
        TrainingRecipe(time_reverse_swaps=[[0, 0]])
    with pytest.raises(ValueError, match="time_reverse_swaps must be pairs"):
        TrainingRecipe(time_reverse_swaps=[[0, 1, 2]])
    with pytest.raises(ValueError, match="time_reverse_ratio must be in"):
        TrainingRecipe(time_reverse_ratio=1.5)
    with pytest.raises(ValueError, match="3 action columns"):
        get_maskgit_collator(action_config(), TrainingRecipe(time_reverse_ratio=0.5, time_reverse_swaps=[[0, 3]]))
    with pytest.raises(ValueError, match="latent actions"):
        get_maskgit_collator(tiny_config(num_latent_actions=4), TrainingRecipe(time_reverse_ratio=0.5))
