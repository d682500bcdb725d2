"""2-D rotary positions in the spatial attention (GenieConfig.spatial_rope): relative scores, layout, cached inference."""
import pytest
import torch

from genie import GenieConfig, STMaskGIT
from genie.config import ConfigError
from genie.inference import generate
from genie.reference import generate_uncached
from genie.rope import apply_rope, rope_tables
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


def rope_model(spatial_rope: bool) -> STMaskGIT:
    return make_model(qk_norm=True, spatial_rope=spatial_rope)


def test_rope_keeps_the_weights_layout_and_changes_the_logits():
    plain, rotary = rope_model(False), rope_model(True)
    assert plain.state_dict().keys() == rotary.state_dict().keys()
    rotary.load_state_dict(plain.state_dict())  # strict: no extra saved tensors
    x = torch.randint(0, 64 ** 2, (1, 6, 4, 4), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert not torch.allclose(plain.logits(x), rotary.logits(x), atol=1e-3)


def test_rope_cached_generation_equals_full_recomputation():
    model = rope_model(True)
    x = torch.randint(0, 64 ** 2, (2, 6, 4, 4), generator=torch.Generator().manual_seed(2))
    (cached_tokens, cached_logits), (full_tokens, full_logits) = [
        fn(model, x[:, :2], 4, 2, 1.0, generator=torch.Generator().manual_seed(3)) for fn in (generate, generate_uncached)]
    torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
    assert torch.equal(cached_tokens, full_tokens)


def test_rope_needs_a_head_width_divisible_by_4():
    with pytest.raises(ConfigError, match="spatial_rope"):
        GenieConfig(num_layers=1, num_heads=2, d_model=12, T=4, S=16, image_vocab_size=64 ** 2, num_prompt_frames=1,
                    spatial_rope=True)
