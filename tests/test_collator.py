"""MaskGIT training collator: masking and corruption invariants, rates, determinism."""
import math

import numpy as np
import pytest
import torch

from data import RawTokenDataset, TokenDatasetError, write_token_dataset
from genie.config import GenieConfig, TrainingRecipe
from genie.factorization import factorize_token_ids
from genie.masking import MaskGITBatch, get_maskgit_collator

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
        assert batch.target_ids is None and batch.actions is None and batch.latent_actions is None
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
def test_teacher_forced_examples_mask_whole_frames_over_clean_context(non_mlm_ratio):
    config = tiny_config()
    recipe = TrainingRecipe(whole_frame_mask_ratio=1.0, max_corrupt_rate=0.0, non_mlm_ratio=non_mlm_ratio)
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


@pytest.mark.parametrize("ratio", [0.5, 1.0])
def test_clean_prefix_ratio_starts_whole_frame_masks_after_up_to_the_prompt(ratio):
    """A share of the examples starts its periodic whole-frame masks anywhere in 1..num_prompt_frames, so a target
    follows a long clean run (as a rollout's first frame follows its prompt); the masks keep their period."""
    config = tiny_config(T=12, num_prompt_frames=6)
    recipe = TrainingRecipe(whole_frame_mask_ratio=1.0, clean_prefix_ratio=ratio, max_corrupt_rate=0.0)
    collate = get_maskgit_collator(config, recipe, seed=0)
    firsts = []
    for step in range(40):
        batch = collate(make_features(8, T=12, seed=step))
        whole = (frames(batch.input_ids) == config.mask_token_id).all(-1)
        assert whole.any(dim=1).all() and not (whole[:, 1:] & whole[:, :-1]).any()
        assert {int(g) for row in whole for g in torch.diff(torch.nonzero(row).flatten())} <= {2, 3}
        firsts += whole.float().argmax(1).tolist()
    counts = torch.bincount(torch.tensor(firsts), minlength=8)
    assert counts[0] == 0 and counts[7:].sum() == 0 and (counts[1:7] > 0).all()
    share_late = counts[4:7].sum().item() / len(firsts)  # starts the default's first period never reaches
    assert abs(share_late - ratio * 3 / 6) < 0.08


def test_whole_frame_mask_ratio_mixes_in_published_masking():
    config = tiny_config()
    collate = get_maskgit_collator(config, TrainingRecipe(whole_frame_mask_ratio=0.5), seed=0)
    whole, partial = 0, 0
    for step in range(40):
        per_frame = (frames(collate(make_features(8, seed=step)).input_ids) == config.mask_token_id).sum(-1)
        example_is_whole = ((per_frame == 0) | (per_frame == S)).all(dim=1)
        whole += int(example_is_whole.sum())
        partial += int((~example_is_whole).sum())
    assert 0.3 < whole / (whole + partial) < 0.75  # ~half (published masks are rarely whole-frame by chance)


@pytest.mark.parametrize("partial_ratio", [0.0, 0.5])
def test_two_stream_batches_keep_a_clean_context_and_mask_every_later_frame(partial_ratio):
    config = action_config()
    recipe = TrainingRecipe(two_stream_ratio=1.0, two_stream_partial_ratio=partial_ratio, max_corrupt_rate=0.0,
                            non_mlm_ratio=1.0)
    collate = get_maskgit_collator(config, recipe, seed=0)
    whole = partly = 0
    for step in range(20):
        features = make_features(4, seed=step, actions=True)
        batch = collate(features)
        assert batch.target_ids is not None and batch.actions is not None and batch.latent_actions is None
        assert batch.target_ids.shape == batch.input_ids.shape == (4, T, H, W)
        assert torch.equal(batch.actions, torch.stack([f["actions"]["a"] for f in features]))
        context, targets, labels = frames(batch.input_ids), frames(batch.target_ids), frames(batch.labels)
        assert torch.equal(context, labels), "the context is whole and, without corruption, clean"
        masked = targets == config.mask_token_id
        assert not masked[:, 0].any() and masked[:, 1:].any(-1).all(), "every frame >= 1 is a target"
        assert torch.equal(targets[~masked], labels[~masked])
        per_frame = masked[:, 1:].sum(-1)
        whole += int((per_frame == S).sum())
        partly += int((per_frame < S).sum())
    if partial_ratio == 0.0:
        assert partly == 0
    else:
        assert 0.25 < partly / (whole + partly) < 0.5  # ~half drawn partial, some of those masked whole anyway


def test_two_stream_ratio_mixes_batches_and_keeps_light_corruption():
    config = tiny_config()
    collate = get_maskgit_collator(config, TrainingRecipe(two_stream_ratio=0.5, max_corrupt_rate=1.0), seed=1)
    kinds = []
    for step in range(40):
        batch = collate(make_features(2, seed=step))
        kinds.append(batch.target_ids is not None)
        if kinds[-1]:
            context = batch.input_ids
            assert not (context == config.mask_token_id).any()
            assert (context >= 0).all() and (context < VOCAB).all()
    assert 10 < sum(kinds) < 30
    assert any(not torch.equal(b.input_ids, b.labels) for b in
               [collate(make_features(2, seed=s)) for s in range(40)] if b.target_ids is not None), \
        "the context gets step 1's random corruption"


def test_context_noise_corrupts_only_the_chosen_examples_unmasked_frames_at_their_levels():
    config = tiny_config()
    recipe = TrainingRecipe(whole_frame_mask_ratio=1.0, max_corrupt_rate=0.0, context_noise_ratio=0.5,
                            context_noise_max=0.8)
    collate = get_maskgit_collator(config, recipe, seed=0)
    replaced, expected, chosen, total = 0.0, 0.0, 0, 0
    for step in range(60):
        batch = collate(make_features(8, seed=step))
        x, labels, level = frames(batch.input_ids), frames(batch.labels), batch.context_noise
        assert level.shape == (8, T) and (level >= 0).all() and (level <= 0.8).all()
        whole = (x == config.mask_token_id).all(-1)
        assert (level[:, 0] == 0).all() and (level[whole] == 0).all(), "frame 0 and targets have no level"
        changed = (x != labels) & (x != config.mask_token_id)
        assert not changed[level == 0].any(), "only frames with a level are corrupted"
        replaced += changed.float().sum().item()
        expected += (level.unsqueeze(-1) * (1 - 1 / VOCAB)).expand(-1, -1, S).sum().item()
        chosen += int((level > 0).any(1).sum())
        total += 8
    assert 0.35 < chosen / total < 0.65  # about context_noise_ratio of the examples
    assert abs(replaced / expected - 1) < 0.1  # each token replaced with its frame's probability


def test_without_context_noise_batches_carry_no_levels_and_draw_as_before():
    config = tiny_config()
    plain = get_maskgit_collator(config, TrainingRecipe(whole_frame_mask_ratio=1.0), seed=0)
    noisy = get_maskgit_collator(config, TrainingRecipe(whole_frame_mask_ratio=1.0, context_noise_ratio=1.0,
                                                        context_noise_max=0.0), seed=0)
    a, b = plain(make_features(4)), noisy(make_features(4))
    assert a.context_noise is None
    # the noise is drawn after everything else, so a zero level leaves the batch as the plain recipe draws it
    assert torch.equal(a.input_ids, b.input_ids) and (b.context_noise == 0).all()


def test_speed_jitter_scales_the_named_columns_of_each_window_by_one_factor():
    features = make_features(64, seed=4, actions=True)
    features[3]["actions"]["a"][2] = float("nan")  # an unknown row stays unknown
    recipe = TrainingRecipe(speed_jitter=0.5, speed_jitter_columns=[0, 2])
    plain = get_maskgit_collator(action_config(), TrainingRecipe(), seed=5)(features)
    jittered = get_maskgit_collator(action_config(), recipe, seed=5)(features)
    # the tokens and masks are the same batch's: only the actions change
    assert torch.equal(jittered.input_ids, plain.input_ids) and torch.equal(jittered.labels, plain.labels)
    torch.testing.assert_close(jittered.actions[..., 1], plain.actions[..., 1], equal_nan=True)
    assert jittered.actions[3, 2].isnan().all()
    ratio_BTC = jittered.actions[..., [0, 2]] / plain.actions[..., [0, 2]]
    scale_B = ratio_BTC[:, 0, 0]
    known_BTC = ~ratio_BTC.isnan()
    torch.testing.assert_close(ratio_BTC[known_BTC], scale_B[:, None, None].expand_as(ratio_BTC)[known_BTC])
    assert (scale_B >= 1 / 1.5 - 1e-6).all() and (scale_B <= 1.5 + 1e-6).all()
    # log-uniform: the factors spread over the range, above and below 1 about equally often
    assert scale_B.log().abs().max() > 0.8 * math.log(1.5) and 16 < int((scale_B > 1).sum()) < 48


def test_speed_jitter_off_and_its_columns_are_checked():
    features = make_features(2, seed=6, actions=True)
    off = get_maskgit_collator(action_config(), TrainingRecipe(speed_jitter_columns=[0]), seed=7)(features)
    assert torch.equal(off.actions, get_maskgit_collator(action_config(), TrainingRecipe(), seed=7)(features).actions)
    with pytest.raises(ValueError, match=r"speed_jitter_columns \[3\] name columns beyond the model's 3"):
        get_maskgit_collator(action_config(), TrainingRecipe(speed_jitter=0.5, speed_jitter_columns=[3]),
                             seed=7)(features)
    # a model without real actions has nothing to scale
    assert get_maskgit_collator(tiny_config(), TrainingRecipe(speed_jitter=0.5, speed_jitter_columns=[0]),
                                seed=7)(features).actions is None
