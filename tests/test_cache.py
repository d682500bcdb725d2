"""Cached inference (temporal KV cache) equals full recomputation: logits and samples, generate and teacher_forced."""
import pytest
import torch

from genie import GenieConfig, STMaskGIT, TemporalKVCache
from genie.inference import check_frames, generate_frames, run_frames, teacher_forced
from genie.reference import generate_uncached, teacher_forced_uncached
from genie.transformer import TemporalMode


def make_model(qk_norm: bool, seed: int = 0, **config_overrides) -> STMaskGIT:
    torch.manual_seed(seed)
    config = GenieConfig(num_layers=2, num_heads=4, d_model=32, T=6, S=16, image_vocab_size=64 ** 2,
                         num_prompt_frames=2, qk_norm=qk_norm, **config_overrides)
    model = STMaskGIT(config)
    model.init_weights()
    with torch.no_grad():  # larger than the init so that logits differ clearly between positions and frames
        for module in model.modules():
            if isinstance(module, torch.nn.Linear):
                module.weight.normal_(0, module.in_features ** -0.5)
        model.pos_embed_TSC.normal_(0, 1.0)
        for embed in model.token_embed.factored_embeds:
            embed.weight.normal_(0, 1.0)
    return model.eval()


def tokens(model: STMaskGIT, B: int, T: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, model.config.image_vocab_size, (B, T, model.config.H, model.config.W), generator=g)


@pytest.mark.parametrize("qk_norm", [False, True])
@pytest.mark.parametrize("maskgit_steps", [1, 2, 3, 4])
def test_teacher_forced_cached_equals_full_recomputation(qk_norm, maskgit_steps):
    model = make_model(qk_norm)
    x = tokens(model, B=2, T=6)
    modes = ((1.0, "random"), (0.0, "random"), (1.0, "greedy")) if maskgit_steps == 2 else ((1.0, "random"),)
    for temperature, unmask_mode in modes:
        runs = [fn(model, x, maskgit_steps, temperature, unmask_mode, generator=torch.Generator().manual_seed(7))
                for fn in (teacher_forced, teacher_forced_uncached)]
        (cached_samples, cached_logits), (full_samples, full_logits) = runs
        assert cached_logits.shape == (2, 64, 2, 5, 4, 4)
        torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
        assert torch.equal(cached_samples, full_samples)


def test_teacher_forced_logits_are_those_of_the_masked_window():
    """Independent of the implementation's uncached path: target t's first-step logits = logits of frame t
    for the window with ground truth before t and masks from t on."""
    model = make_model(qk_norm=False, seed=1)
    x = tokens(model, B=2, T=5, seed=1)
    _, logits_BVFTHW = teacher_forced(model, x, maskgit_steps=1)
    for t in (1, 3, 4):
        window = x.clone()
        window[:, t:] = model.mask_token_id
        with torch.no_grad():
            expected = model.logits(window)[:, :, :, t]
        torch.testing.assert_close(logits_BVFTHW[:, :, :, t - 1], expected, atol=1e-5, rtol=1e-5)
    # the targets' logits really depend on their context: different frames give different predictions
    assert not torch.allclose(logits_BVFTHW[:, :, :, 0], logits_BVFTHW[:, :, :, 1], atol=1e-3)


@pytest.mark.parametrize("qk_norm", [False, True])
@pytest.mark.parametrize("maskgit_steps", [1, 2, 3, 4])
def test_generate_cached_equals_full_recomputation(qk_norm, maskgit_steps):
    model = make_model(qk_norm)
    prompt = tokens(model, B=2, T=2, seed=2)
    for temperature in ((0.0, 1.0) if maskgit_steps == 2 else (1.0,)):
        runs = [fn(model, prompt, 4, maskgit_steps, temperature, generator=torch.Generator().manual_seed(3))
                for fn in (generate_frames, generate_uncached)]
        (cached_tokens, cached_logits), (full_tokens, full_logits) = runs
        assert cached_tokens.shape == (2, 6, 4, 4) and cached_logits.shape == (2, 64, 2, 4, 4, 4)
        assert torch.equal(cached_tokens[:, :2], prompt)
        assert (cached_tokens != model.mask_token_id).all()
        torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
        assert torch.equal(cached_tokens, full_tokens)


def test_run_frames_matches_full_logits_frame_by_frame():
    model = make_model(qk_norm=True, seed=4)
    x = tokens(model, B=1, T=6, seed=4)
    with torch.no_grad():
        full = model.logits(x)  # (B, V, F, T, H, W)
        cache = TemporalKVCache(model.config.num_layers, 6)
        assert run_frames(model, x[:, :2], 0, cache, TemporalMode.PREFILL, commit=2) is None
        for t in range(2, 6):
            logits = run_frames(model, x[:, t:t + 1], t, cache, commit=1)  # (B, V, F, 1, H, W)
            torch.testing.assert_close(logits[:, :, :, 0], full[:, :, :, t], atol=1e-5, rtol=1e-5)
    assert cache.length == 6


def test_generation_beyond_position_embeddings_and_bad_cache_use_raise():
    model = make_model(qk_norm=False)
    prompt = tokens(model, B=1, T=4)
    with pytest.raises(ValueError, match="position embeddings for T = 6"):
        generate_frames(model, prompt, 3)
    with pytest.raises(ValueError, match="at least one"):
        generate_frames(model, prompt, 0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        teacher_forced(model, prompt[:, :1])
    cache = TemporalKVCache(model.config.num_layers, 3)
    with pytest.raises(ValueError, match="must follow the 0 cached frames"):
        check_frames(model, prompt[:, :1], 1, cache, TemporalMode.APPEND)
    with pytest.raises(ValueError, match="need a cache of frames"):
        check_frames(model, prompt[:, :1], 1, cache, TemporalMode.TARGETS)
    with pytest.raises(ValueError, match="exceed its capacity"):
        run_frames(model, prompt, 0, cache)
    with pytest.raises(ValueError, match="CAUSAL takes no KV cache"):
        model.predict_frames(prompt, kv_cache=cache)
