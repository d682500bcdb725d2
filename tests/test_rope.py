"""Rotary positions (GenieConfig.spatial_rope, temporal_rope): relative scores, layout, cached inference."""
import pytest
import torch

from genie import GenieConfig, STMaskGIT
from genie.config import ConfigError
from genie.inference import generate_frames, teacher_forced
from genie.reference import generate_uncached, teacher_forced_uncached
from genie.transformer import apply_rope, rope_tables
from tests.test_cache import make_model


def test_scores_depend_only_on_the_relative_offset():
    H = W = 6
    cos, sin = rope_tables(H, W, head_dim=16)
    g = torch.Generator().manual_seed(0)
    q, k = torch.randn(16, generator=g), torch.randn(16, generator=g)

    def score(query_rc, key_rc):
        qi, ki = query_rc[0] * W + query_rc[1], key_rc[0] * W + key_rc[1]
        q_rot = apply_rope(q.expand(H * W, 16), cos, sin)[qi]
        k_rot = apply_rope(k.expand(H * W, 16), cos, sin)[ki]
        return float(q_rot @ k_rot)

    offset_score = score((1, 1), (3, 2))  # key two rows down, one column right
    assert score((3, 4), (5, 5)) == pytest.approx(offset_score, abs=1e-5)
    assert score((0, 0), (2, 1)) == pytest.approx(offset_score, abs=1e-5)
    # a different offset scores differently, in either axis
    assert abs(score((1, 1), (3, 3)) - offset_score) > 1e-3
    assert abs(score((1, 1), (2, 2)) - offset_score) > 1e-3
    # rotations keep lengths; position (0, 0) is unrotated
    x = torch.randn(H * W, 16, generator=g)
    assert torch.allclose(apply_rope(x, cos, sin).norm(dim=-1), x.norm(dim=-1), atol=1e-5)
    assert torch.equal(apply_rope(x, cos, sin)[0], x[0])


def test_temporal_scores_depend_only_on_how_many_frames_back_the_key_lies():
    block = make_model(qk_norm=True, temporal_rope=True).decoder.layers[0]
    T, head_dim = block.rope_cos_TD.shape
    g = torch.Generator().manual_seed(0)
    q, k = torch.randn(head_dim, generator=g), torch.randn(head_dim, generator=g)

    def score(query_frame, key_frame, first_frame=0):
        frames = torch.arange(first_frame, T)
        q_rot = block.rotate_in_time(q.expand(1, 1, T - first_frame, head_dim), first_frame)[0, 0]
        k_rot = block.rotate_in_time(k.expand(1, 1, T - first_frame, head_dim), first_frame)[0, 0]
        return float(q_rot[frames == query_frame][0] @ k_rot[frames == key_frame][0])

    two_back = score(3, 1)
    assert score(5, 3) == pytest.approx(two_back, abs=1e-5)
    assert score(4, 2, first_frame=2) == pytest.approx(two_back, abs=1e-5)  # a cached pass turns by frame, not slot
    assert abs(score(3, 2) - two_back) > 1e-3
    assert torch.equal(block.rotate_in_time(q.expand(1, 1, 1, head_dim), 0)[0, 0, 0], q)  # frame 0 unturned


def rope_model(**rope) -> STMaskGIT:
    return make_model(qk_norm=True, **rope)


@pytest.mark.parametrize("rope", ["spatial_rope", "temporal_rope"])
def test_rope_keeps_the_weights_layout_and_changes_the_logits(rope):
    plain, rotary = rope_model(), rope_model(**{rope: True})
    assert plain.state_dict().keys() == rotary.state_dict().keys()
    rotary.load_state_dict(plain.state_dict())  # strict: no extra saved tensors
    x = torch.randint(0, 64 ** 2, (1, 6, 4, 4), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        plain_logits, rotary_logits = plain.logits(x), rotary.logits(x)
    assert not torch.allclose(plain_logits, rotary_logits, atol=1e-3)
    if rope == "temporal_rope":  # frame 0 attends only to itself, unturned: the same as without
        torch.testing.assert_close(rotary_logits[:, :, :, 0], plain_logits[:, :, :, 0], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("rope", [dict(spatial_rope=True), dict(temporal_rope=True),
                                  dict(spatial_rope=True, temporal_rope=True)])
def test_rope_cached_inference_equals_full_recomputation(rope):
    model = rope_model(**rope)
    x = torch.randint(0, 64 ** 2, (2, 6, 4, 4), generator=torch.Generator().manual_seed(2))
    (cached_tokens, cached_logits), (full_tokens, full_logits) = [
        fn(model, x[:, :2], 4, 2, 1.0, generator=torch.Generator().manual_seed(3))
        for fn in (generate_frames, generate_uncached)]
    torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
    assert torch.equal(cached_tokens, full_tokens)
    (cached_samples, cached_logits), (full_samples, full_logits) = [
        fn(model, x, 2, 1.0, "random", generator=torch.Generator().manual_seed(4))
        for fn in (teacher_forced, teacher_forced_uncached)]
    torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
    assert torch.equal(cached_samples, full_samples)


@pytest.mark.parametrize("rope", ["spatial_rope", "temporal_rope"])
def test_rope_needs_a_head_width_divisible_by_4(rope):
    with pytest.raises(ConfigError, match=rope):
        GenieConfig(num_layers=1, num_heads=2, d_model=12, T=4, S=16, image_vocab_size=64 ** 2, num_prompt_frames=1,
                    **{rope: True})
