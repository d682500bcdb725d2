"""STMaskGIT: published parameter layout, an independent reference forward, loss, checkpoint round trip, errors."""
import json
import math
from pathlib import Path

import pytest
import safetensors.torch
import torch
import torch.nn.functional as F

import genie
from common.config import ConfigError
from common.errors import CheckpointError
from genie.decoding import DecodingConfig
from genie import GenieConfig, MaskGITBatch, STMaskGIT, TrainingRecipe
from genie.checkpoint import load_state_dict_checked
from genie.reference import full_logits_loss

CONFIG_DIR = Path(genie.__file__).parent / "configs"


def tiny_config(**overrides) -> GenieConfig:
    kwargs = dict(num_layers=2, num_heads=4, d_model=32, T=4, S=16, image_vocab_size=64 ** 2, num_prompt_frames=2)
    kwargs.update(overrides)
    return GenieConfig(**kwargs)


def published_state_dict(config: GenieConfig, seed: int = 0) -> dict:
    """Random weights under the docs/formats.md §3 parameter names, written out by hand (not from the model)."""
    g = torch.Generator().manual_seed(seed)
    d, V, F_ = config.d_model, config.factored_vocab_size, config.num_factored_vocabs
    hidden, hd = int(d * config.mlp_ratio), d // config.num_heads

    def rnd(*shape, std=0.3):
        return torch.randn(*shape, generator=g) * std

    sd = {"pos_embed_TSC": rnd(1, config.T, config.S, d, std=1.0),
          "token_embed.mask_token_embed": rnd(1, d, std=1.0),
          "out_x_proj.weight": rnd(F_ * V, d), "out_x_proj.bias": rnd(F_ * V)}
    for k in range(F_):
        sd[f"token_embed.factored_embeds.{k}.weight"] = rnd(V, d, std=1.0)
    for i in range(config.num_layers):
        p = f"decoder.layers.{i}."
        for attn in ("spatial_attn", "temporal_attn"):
            sd[p + attn + ".qkv.weight"] = rnd(3 * d, d, std=d ** -0.5)
            sd[p + attn + ".proj.weight"] = rnd(d, d, std=d ** -0.5)
            sd[p + attn + ".proj.bias"] = rnd(d, std=0.1)
            if config.qk_norm:
                sd[p + attn + ".norm.weight"] = 1 + rnd(hd, std=0.1)
                sd[p + attn + ".norm.bias"] = rnd(hd, std=0.1)
        if not config.qk_norm:
            for norm in ("norm1", "norm2"):
                sd[p + norm + ".weight"] = 1 + rnd(d, std=0.1)
                sd[p + norm + ".bias"] = rnd(d, std=0.1)
        sd[p + "mlp.fc1.weight"] = rnd(hidden, d, std=d ** -0.5)
        sd[p + "mlp.fc1.bias"] = rnd(hidden, std=0.1)
        sd[p + "mlp.fc2.weight"] = rnd(d, hidden, std=hidden ** -0.5)
        sd[p + "mlp.fc2.bias"] = rnd(d, std=0.1)
    return sd


def reference_logits(sd: dict, config: GenieConfig, x_BTHW: torch.Tensor) -> torch.Tensor:
    """Straightforward float64 forward of the published block semantics -> logits (B, F*V, T, H, W)."""
    sd = {k: v.double() for k, v in sd.items()}
    B, T, H, W = x_BTHW.shape
    S, d, nh, V = H * W, config.d_model, config.num_heads, config.factored_vocab_size
    hd = d // nh
    scale = 8 / hd if config.use_mup else hd ** -0.5

    def layer_norm(x, w, b):
        mu = x.mean(-1, keepdim=True)
        var = ((x - mu) ** 2).mean(-1, keepdim=True)
        return (x - mu) / torch.sqrt(var + 1e-5) * w + b

    def attention(x_NLC, p, causal):
        qkv = x_NLC @ sd[p + ".qkv.weight"].T
        q, k, v = (qkv[..., i * d:(i + 1) * d].reshape(*x_NLC.shape[:2], nh, hd) for i in range(3))
        if config.qk_norm:
            q = layer_norm(q, sd[p + ".norm.weight"], sd[p + ".norm.bias"])
            k = layer_norm(k, sd[p + ".norm.weight"], sd[p + ".norm.bias"])
        scores = torch.einsum("nlhd,nmhd->nhlm", q, k) * scale
        if causal:
            L = x_NLC.shape[1]
            scores = scores.masked_fill(torch.ones(L, L, dtype=torch.bool).triu(1), float("-inf"))
        out = torch.einsum("nhlm,nmhd->nlhd", scores.softmax(-1), v).reshape(x_NLC.shape)
        return out @ sd[p + ".proj.weight"].T + sd[p + ".proj.bias"]

    ids = x_BTHW.reshape(B, T, S)
    is_mask = ids == config.image_vocab_size
    f0, f1 = ids % V, (ids // V) % V
    h = sd["token_embed.factored_embeds.0.weight"][f0] + sd["token_embed.factored_embeds.1.weight"][f1]
    h[is_mask] = sd["token_embed.mask_token_embed"][0]
    h = h + sd["pos_embed_TSC"][0, :T]
    for i in range(config.num_layers):
        p = f"decoder.layers.{i}."
        x = h.reshape(B * T, S, d)
        normed = x if config.qk_norm else layer_norm(x, sd[p + "norm1.weight"], sd[p + "norm1.bias"])
        x = x + attention(normed, p + "spatial_attn", causal=False)
        x = x.reshape(B, T, S, d).transpose(1, 2).reshape(B * S, T, d)
        x = x + attention(x, p + "temporal_attn", causal=True)  # no norm before temporal attention
        normed = x if config.qk_norm else layer_norm(x, sd[p + "norm2.weight"], sd[p + "norm2.bias"])
        hidden = normed @ sd[p + "mlp.fc1.weight"].T + sd[p + "mlp.fc1.bias"]
        hidden = 0.5 * hidden * (1 + torch.erf(hidden / math.sqrt(2)))
        x = x + hidden @ sd[p + "mlp.fc2.weight"].T + sd[p + "mlp.fc2.bias"]
        h = x.reshape(B, S, T, d).transpose(1, 2)
    if config.use_mup:
        h = h / (d / 256)
    logits = h @ sd["out_x_proj.weight"].T + sd["out_x_proj.bias"]  # (B, T, S, F*V)
    return logits.permute(0, 3, 1, 2).reshape(B, -1, T, H, W)


def write_published_checkpoint(path: Path, config: GenieConfig, sd: dict) -> None:
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps(config.to_dict(), sort_keys=True, indent=2))
    safetensors.torch.save_file(sd, str(path / "model.safetensors"))


def random_tokens(config: GenieConfig, B: int, T: int, seed: int = 0, mask_rate: float = 0.3) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, config.image_vocab_size, (B, T, config.H, config.W), generator=g)
    return x.masked_fill(torch.rand(x.shape, generator=g) < mask_rate, config.mask_token_id)


def flat_logits(logits_BVFTHW: torch.Tensor) -> torch.Tensor:
    """The model's factored logits (B, V, F, T, H, W) in the published readout order (B, F*V, T, H, W)."""
    B, V, F_ = logits_BVFTHW.shape[:3]
    return logits_BVFTHW.transpose(1, 2).reshape(B, F_ * V, *logits_BVFTHW.shape[3:])


def test_35m_config_has_published_names_shapes_and_size():
    config = GenieConfig.from_pretrained(CONFIG_DIR / "magvit_n32_h8_d256.json")
    shapes = {k: tuple(v.shape) for k, v in STMaskGIT(config).state_dict().items()}
    d = 256
    expected_layer0 = {
        "norm1.weight": (d,), "norm1.bias": (d,), "spatial_attn.qkv.weight": (3 * d, d),
        "spatial_attn.proj.weight": (d, d), "spatial_attn.proj.bias": (d,), "temporal_attn.qkv.weight": (3 * d, d),
        "temporal_attn.proj.weight": (d, d), "temporal_attn.proj.bias": (d,), "norm2.weight": (d,),
        "norm2.bias": (d,), "mlp.fc1.weight": (4 * d, d), "mlp.fc1.bias": (4 * d,), "mlp.fc2.weight": (d, 4 * d),
        "mlp.fc2.bias": (d,)}
    expected = {"pos_embed_TSC": (1, 16, 256, d), "token_embed.mask_token_embed": (1, d),
                "token_embed.factored_embeds.0.weight": (512, d), "token_embed.factored_embeds.1.weight": (512, d),
                "out_x_proj.weight": (1024, d), "out_x_proj.bias": (1024,)}
    expected.update({f"decoder.layers.{i}.{k}": v for i in range(32) for k, v in expected_layer0.items()})
    assert shapes == expected
    assert round(sum(math.prod(s) for s in shapes.values()) / 1e6, 1) == 35.2


def test_8_layer_config_is_the_benchmark_shape():
    config = GenieConfig.from_pretrained(CONFIG_DIR / "magvit_n8_h8_d256.json")
    assert (config.num_layers, config.num_heads, config.d_model, config.T, config.S) == (8, 8, 256, 16, 256)


@pytest.mark.parametrize("qk_norm", [False, True])
def test_published_layout_checkpoint_matches_reference_forward(tmp_path, qk_norm):
    config = tiny_config(qk_norm=qk_norm)
    sd = published_state_dict(config)
    write_published_checkpoint(tmp_path / "ckpt", config, sd)
    model = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    assert not model.training
    x = random_tokens(config, B=2, T=4)
    with torch.no_grad():
        logits = model.logits(x)
    ref = reference_logits(sd, config, x)
    assert logits.shape == (2, 64, 2, 4, 4, 4)
    assert ref.abs().max() > 1  # the comparison is not between near-zero numbers
    torch.testing.assert_close(flat_logits(logits).double(), ref, atol=2e-4, rtol=1e-4)


def test_mup_scales_attention_and_readout(tmp_path):
    config = tiny_config(use_mup=True, d_model=64, num_heads=4)
    sd = published_state_dict(config, seed=1)
    model = STMaskGIT(config)
    load_state_dict_checked(model, sd)
    x = random_tokens(config, B=1, T=3, seed=1)
    with torch.no_grad():
        logits = model.logits(x)
    torch.testing.assert_close(flat_logits(logits).double(), reference_logits(sd, config, x), atol=2e-4, rtol=1e-4)
    plain = STMaskGIT(tiny_config(d_model=64, num_heads=4))
    load_state_dict_checked(plain, sd)
    with torch.no_grad():
        assert not torch.allclose(plain.logits(x), logits, atol=1e-2)


def sharp_readout_model(config: GenieConfig) -> STMaskGIT:
    """A freshly initialised model whose readout is large enough that argmax and CE differ between tokens."""
    model = STMaskGIT(config)
    model.init_weights()
    with torch.no_grad():
        model.out_x_proj.weight.normal_(0, 1.0)
    return model


def test_loss_is_factored_ce_over_masked_tokens_of_later_frames():
    config = tiny_config()
    model = sharp_readout_model(config)
    labels = random_tokens(config, B=2, T=4, mask_rate=0.0)
    g = torch.Generator().manual_seed(3)
    inputs = labels.masked_fill(torch.rand(labels.shape, generator=g) < 0.5, config.mask_token_id)
    out = full_logits_loss(model, MaskGITBatch(inputs, labels))

    V = config.factored_vocab_size
    logp = model.logits(inputs).detach().transpose(1, 2).log_softmax(dim=2)  # (B, F, V, T, H, W)
    ce = -(logp[:, 0].gather(1, (labels % V).unsqueeze(1)) + logp[:, 1].gather(1, (labels // V).unsqueeze(1)))
    ce = ce.squeeze(1)  # (B, T, H, W)
    right = (logp[:, 0].argmax(1) == labels % V) & (logp[:, 1].argmax(1) == labels // V)
    relevant = (inputs == config.mask_token_id)
    relevant[:, 0] = False  # frame 0 never counts
    assert relevant.sum() > 10
    torch.testing.assert_close(out.loss.detach(), ce[relevant].mean())
    torch.testing.assert_close(out.acc, right[relevant].float().mean())
    out.loss.backward()
    assert model.pos_embed_TSC.grad is not None


VARIANTS = {"plain": {}, "actions": dict(num_latent_actions=3, action_dropout=0.0), "copy": dict(copy_radius=1),
            "copy_match": dict(copy_radius=1, copy_match_input=True),
            "rotary": dict(spatial_rope=True, temporal_rope=True)}


def variant_model(variant: str) -> STMaskGIT:
    model = sharp_readout_model(tiny_config(**VARIANTS[variant]))
    if model.copy_head is not None:  # scores that differ between neighbours, so that a wrong source shows
        with torch.no_grad():
            model.copy_head.score_proj.weight.normal_(0, 1.0)
            if model.copy_head.match_proj is not None:
                model.copy_head.match_proj.weight.normal_(0, 1.0)
    if model.config.temporal_rope:  # attention far from uniform over frames, so that a wrong frame offset shows
        with torch.no_grad():
            for layer in model.decoder.layers:
                layer.temporal_attn.qkv.weight.normal_(0, 1.0)
    return model


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_masked_only_readout_gives_same_loss_acc_and_gradients(variant):
    """The training loss reads out only the counted tokens: same loss, acc and gradients as from every token's
    logits (genie.reference.full_logits_loss)."""
    uses_actions = variant == "actions"
    model = variant_model(variant)
    config = model.config
    model = sharp_readout_model(config)
    labels = random_tokens(config, B=2, T=4, mask_rate=0.0)
    g = torch.Generator().manual_seed(5)
    masked = torch.rand(labels.shape, generator=g) < 0.5
    masked[:, 0, 0, 0] = True  # a masked token in frame 0, which must not count
    inputs = labels.masked_fill(masked, config.mask_token_id)
    batch = MaskGITBatch(inputs, labels, latent_actions=torch.randint(0, 3, (2, 4), generator=g) if uses_actions
                         else None)

    grads = []
    outs = []
    for loss_fn in (full_logits_loss, lambda m, b: m(b)):
        model.zero_grad()
        out = loss_fn(model, batch)
        out.loss.backward()
        outs.append(out)
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    full, masked_only = outs
    torch.testing.assert_close(masked_only.loss, full.loss)
    torch.testing.assert_close(masked_only.acc, full.acc)
    assert grads[0].keys() == grads[1].keys() and grads[0]["out_x_proj.weight"].abs().sum() > 0
    for name in grads[0]:
        torch.testing.assert_close(grads[1][name], grads[0][name], atol=1e-6, rtol=1e-5)


def test_gradient_checkpointing_gives_the_same_loss_and_gradients_with_less_saved():
    config = tiny_config(mlp_drop=0.1)  # dropout: the recomputation must replay the same random mask
    model = sharp_readout_model(config).train()
    labels = random_tokens(config, B=2, T=4, mask_rate=0.0)
    inputs = labels.masked_fill(torch.rand(labels.shape, generator=torch.Generator().manual_seed(2)) < 0.5,
                                config.mask_token_id)
    results = []
    for recompute in (False, True):
        model.decoder.gradient_checkpointing = recompute
        model.zero_grad()
        saved = []
        torch.manual_seed(0)
        with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t.numel()) or t, lambda t: t):
            out = model(MaskGITBatch(inputs, labels))
        out.loss.backward()
        results.append((out.loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}, sum(saved)))
    (loss, grads, saved_plain), (loss_cp, grads_cp, saved_cp) = results
    torch.testing.assert_close(loss_cp, loss)
    for name in grads:
        torch.testing.assert_close(grads_cp[name], grads[name], atol=1e-6, rtol=1e-5)
    assert saved_cp < saved_plain / 2  # only block inputs are kept for the backward pass


@pytest.mark.parametrize("variant", ["plain", "copy", "copy_match"])
def test_self_reveal_fills_masked_tokens_with_the_models_greedy_guesses(variant):
    model = variant_model(variant)
    config = model.config
    x = random_tokens(config, B=3, T=4, mask_rate=0.7)
    torch.manual_seed(0)
    revealed = model._reveal_own_predictions(x, None, 1.0)
    was_masked = x == config.mask_token_id
    assert torch.equal(revealed[~was_masked], x[~was_masked]), "given tokens stay"
    assert torch.equal(revealed[:, 0], x[:, 0]), "frame 0 is never a target"
    filled = was_masked & (revealed != config.mask_token_id)
    later_masked = was_masked[:, 1:].sum().item()
    assert 0.15 < filled.sum().item() / later_masked < 0.6  # a 1 - cos(pi/2 u) share, 0.36 on average
    with torch.no_grad():  # the guesses are the argmax of the full-logits path on the original input
        logits = model.logits(x).transpose(1, 2)  # (B, F, V, T, H, W)
    greedy = logits[:, 0].argmax(1) + config.factored_vocab_size * logits[:, 1].argmax(1)
    assert torch.equal(revealed[filled], greedy[filled])


def test_self_reveal_only_in_training_and_only_for_the_chosen_share():
    config = tiny_config(T=4)
    recipe = TrainingRecipe(self_reveal_ratio=1.0)
    model = sharp_readout_model(config)
    labels = random_tokens(config, B=2, T=4, mask_rate=0.0)
    g = torch.Generator().manual_seed(1)
    x = labels.masked_fill(torch.rand(labels.shape, generator=g) < 0.8, config.mask_token_id)
    torch.manual_seed(5)
    trained_on = model.train()(MaskGITBatch(x, labels), recipe)
    torch.manual_seed(5)
    revealed = model._reveal_own_predictions(x, None, 1.0)
    expected = full_logits_loss(model.eval(), MaskGITBatch(revealed, labels))  # no reveal on this path
    torch.testing.assert_close(trained_on.loss, expected.loss)
    assert not torch.equal(revealed, x)
    evaluated = model.eval()(MaskGITBatch(x, labels), recipe)  # eval mode: nothing revealed
    torch.testing.assert_close(evaluated.loss, full_logits_loss(model, MaskGITBatch(x, labels)).loss)
    assert not torch.allclose(evaluated.loss, trained_on.loss)
    torch.manual_seed(5)
    assert torch.allclose(model.train()(MaskGITBatch(x, labels)).loss, evaluated.loss)  # the published recipe
    assert torch.equal(model._reveal_own_predictions(x, None, 0.0), x)


@pytest.mark.parametrize("field", ["max_corrupt_rate", "non_mlm_ratio", "self_reveal_ratio"])
def test_training_ratios_must_be_probabilities(field):
    with pytest.raises(ConfigError, match=f"{field} must be in \\[0, 1\\]"):
        TrainingRecipe(**{field: 1.5})


def test_one_config_file_holds_architecture_and_recipe_and_legacy_keys_load(tmp_path):
    d = {**tiny_config(qk_norm=True).to_dict(), "max_corrupt_rate": 0.05, "teacher_forced_ratio": 1.0,
         "self_reveal_ratio": 0.5, "guess_temperature": 0.0, "mlp_activation": "gelu"}
    config, recipe = GenieConfig.from_dict(d), TrainingRecipe.from_dict(d)
    assert config == tiny_config(qk_norm=True)
    assert recipe == TrainingRecipe(max_corrupt_rate=0.05, masking="whole_frames", self_reveal_ratio=0.5)
    assert TrainingRecipe.from_dict({"whole_frame_mask_ratio": 0.0}).masking == "published"
    # a removed experiment loads only at the value that had it off; a former share between 0 and 1 is no scheme
    for bad, match in (({"guess_temperature": 1.0}, "guess_temperature was a dropped experiment"),
                       ({"mlp_activation": "swiglu"}, "mlp_activation was a dropped experiment"),
                       ({"whole_frame_mask_ratio": 0.5}, "whole_frame_mask_ratio 0.5 is no longer supported")):
        with pytest.raises(ConfigError, match=match):
            TrainingRecipe.from_dict({**d, **bad})
        with pytest.raises(ConfigError, match=match):
            GenieConfig.from_dict({**d, **bad})
    with pytest.raises(ConfigError, match="unknown key"):
        TrainingRecipe.from_dict({**d, "rope": True})
    # a checkpoint saved with its recipe loads as the architecture; the recipe reads back from the same file
    model = STMaskGIT(config)
    model.save_pretrained(tmp_path / "ckpt", recipe=recipe)
    assert STMaskGIT.from_pretrained(tmp_path / "ckpt").config == config
    assert TrainingRecipe.from_pretrained(tmp_path / "ckpt" / "config.json") == recipe


def test_masked_only_readout_without_masked_tokens_is_zero_loss():
    config = tiny_config()
    model = STMaskGIT(config)
    model.init_weights()
    labels = random_tokens(config, B=1, T=4, mask_rate=0.0)
    out = model(MaskGITBatch(labels, labels))
    assert out.loss.item() == 0.0 and out.acc.item() == 0.0
    out.loss.backward()  # no counted token: still a valid (zero) graph


def test_init_weights():
    model = STMaskGIT(tiny_config(d_model=64, num_heads=4))
    model.init_weights()
    w = model.decoder.layers[0].mlp.fc1.weight
    assert abs(w.std().item() - 0.02) < 0.002
    assert model.decoder.layers[0].mlp.fc1.bias.abs().max() == 0
    assert abs(model.token_embed.factored_embeds[0].weight.std().item() - 0.02) < 0.002
    # sin-cos positions: token-embedding scale, every (frame, token) position distinct, nearer frames more alike
    pos_TSC = model.pos_embed_TSC[0]
    assert abs(pos_TSC.pow(2).mean().sqrt().item() - 0.02) < 0.002
    T, S, _ = pos_TSC.shape
    flat = pos_TSC.reshape(T * S, -1)
    assert torch.cdist(flat, flat).add(torch.eye(T * S)).min() > 1e-4
    frame_dist = [torch.dist(pos_TSC[0], pos_TSC[t]).item() for t in range(1, T)]
    assert frame_dist == sorted(frame_dist)


def test_sincos_positions_of_non_square_grids():
    from genie.model import sincos_pos_embed
    pos = sincos_pos_embed(T=3, S=10, d_model=30)
    assert pos.shape == (1, 3, 10, 30)
    assert torch.isfinite(pos).all() and pos.abs().max() > 0


def test_checkpoint_round_trip(tmp_path):
    config = tiny_config(qk_norm=True, qkv_bias=True)
    model = STMaskGIT(config)
    model.init_weights()
    model.save_pretrained(tmp_path / "ckpt")
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == ["MANIFEST.json", "config.json",
                                                                     "decoding.json", "model.safetensors"]
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt"]  # no temporary directory left behind
    assert json.loads((tmp_path / "ckpt" / "config.json").read_text()) == config.to_dict()
    loaded = STMaskGIT.from_pretrained(str(tmp_path / "ckpt"))
    assert loaded.config == config
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    # saving again into the existing directory replaces the files and keeps unrelated ones
    (tmp_path / "ckpt" / "README.md").write_text("notes")
    model.init_weights()
    model.save_pretrained(tmp_path / "ckpt")
    assert (tmp_path / "ckpt" / "README.md").read_text() == "notes"
    again = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    assert torch.equal(again.out_x_proj.weight, model.out_x_proj.weight)


def test_the_decoding_travels_with_the_checkpoint(tmp_path):
    """decoding.json round-trips; a checkpoint without one (published, or saved before it existed) decodes as the
    published code does; a bad one is an error naming the file; recipe.json is written when given."""
    model = STMaskGIT(tiny_config(copy_radius=1))
    decoding = DecodingConfig(temperature=1.0, copy_bias=2.0, greedy_tokens="best_neighbour", maskgit_steps=3)
    model.set_decoding(decoding)
    model.save_pretrained(tmp_path / "ckpt", run_recipe={"train": {"learning_rate": 0.01}})
    loaded = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    assert loaded.decoding == decoding and loaded.copy_head.copy_bias == 2.0 and loaded.copy_head.best_neighbour_copies
    assert json.loads((tmp_path / "ckpt" / "recipe.json").read_text()) == {"train": {"learning_rate": 0.01}}
    assert {"decoding.json", "recipe.json"} <= set(json.loads((tmp_path / "ckpt" / "MANIFEST.json").read_text())["files"])
    (tmp_path / "ckpt" / "decoding.json").unlink()
    published = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    assert published.decoding == DecodingConfig() and published.copy_head.copy_bias == 0.0
    assert (DecodingConfig().temperature, DecodingConfig().maskgit_steps, DecodingConfig().copy_bias) == (0.0, 2, 0.0)
    (tmp_path / "ckpt" / "decoding.json").write_text(json.dumps({"temperature": 1.0, "top_k": 5}))
    with pytest.raises(ConfigError, match=r"decoding.json: unknown key\(s\) \['top_k'\]"):
        STMaskGIT.from_pretrained(tmp_path / "ckpt")


def test_unknown_config_key_is_an_error(tmp_path):
    config = tiny_config()
    write_published_checkpoint(tmp_path / "ckpt", config, published_state_dict(config))
    d = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    d["rope"] = True
    (tmp_path / "ckpt" / "config.json").write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="rope"):
        STMaskGIT.from_pretrained(tmp_path / "ckpt")


def test_weights_not_matching_config_list_the_keys(tmp_path):
    config = tiny_config(qk_norm=False)
    sd = published_state_dict(tiny_config(qk_norm=True))  # qk_norm weights under a qk_norm=false config
    write_published_checkpoint(tmp_path / "ckpt", config, sd)
    with pytest.raises(CheckpointError) as info:
        STMaskGIT.from_pretrained(tmp_path / "ckpt")
    message = str(info.value)
    assert "model.safetensors" in message
    assert "decoder.layers.0.norm1.weight" in message  # missing
    assert "decoder.layers.0.spatial_attn.norm.weight" in message  # unexpected

    sd = published_state_dict(config)
    sd["out_x_proj.bias"] = torch.zeros(7)
    model = STMaskGIT(config)
    with pytest.raises(CheckpointError, match=r"out_x_proj.bias: checkpoint \(7,\)"):
        load_state_dict_checked(model, sd)


def test_missing_checkpoint_and_offline_hub_id_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        STMaskGIT.from_pretrained(tmp_path / "no" / "such" / "dir")
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "config.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        STMaskGIT.from_pretrained(tmp_path / "half")
    with pytest.raises(FileNotFoundError, match="huggingface-cli download someone/GENIE_TEST --local-dir"):
        STMaskGIT.from_pretrained("someone/GENIE_TEST", local_files_only=True)


def test_bad_token_inputs_are_rejected():
    config = tiny_config()
    model = STMaskGIT(config)
    with pytest.raises(ValueError, match="position embeddings"):
        model.logits(torch.zeros(1, config.T + 1, 4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="H\\*W = S = 16"):
        model.logits(torch.zeros(1, 2, 3, 3, dtype=torch.long))
    with pytest.raises(ValueError, match="token ids must be in"):
        model.logits(torch.full((1, 2, 4, 4), config.mask_token_id + 1))
    with pytest.raises(ValueError, match="input_ids and labels"):
        model(MaskGITBatch(torch.zeros(1, 2, 4, 4, dtype=torch.long), torch.zeros(1, 3, 4, 4, dtype=torch.long)))


def test_bf16_autocast_forward_runs():
    config = tiny_config()
    model = STMaskGIT(config)
    model.init_weights()
    x = random_tokens(config, B=1, T=4)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(MaskGITBatch(x, x))
        logits = model.logits(x)
    assert torch.isfinite(out.loss)
    assert F.cosine_similarity(logits.float().flatten(), model.logits(x).detach().flatten(), 0) > 0.99


@pytest.mark.parametrize("mask", ["none", "causal", "bool"])
def test_bf16_cpu_attention_path_matches_fused_fp32(mask):
    from genie.transformer import SelfAttention
    torch.manual_seed(0)
    attn = SelfAttention(d_model=32, num_heads=4, qk_norm=True)
    q, k, v = (torch.randn(3, 4, 6, 8, requires_grad=True) for _ in range(3))
    attn_mask = torch.rand(6, 6) > 0.3 if mask == "bool" else None
    if attn_mask is not None:
        attn_mask.fill_diagonal_(True)
    kwargs = dict(attn_mask=attn_mask, is_causal=mask == "causal")
    expected = attn.attend(q, k, v, **kwargs)
    expected.square().sum().backward()
    grads = [t.grad.clone() for t in (q, k, v)]
    for t in (q, k, v):
        t.grad = None
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = attn.attend(*(t.bfloat16() for t in (q, k, v)), **kwargs)
    assert got.dtype == torch.bfloat16
    torch.testing.assert_close(got.float(), expected, atol=5e-2, rtol=5e-2)
    got.float().square().sum().backward()
    for grad, t in zip(grads, (q, k, v)):
        assert F.cosine_similarity(t.grad.flatten(), grad.flatten(), 0) > 0.99




def test_a_checkpoint_saved_before_the_removals_loads_and_gives_the_same_logits():
    """tests/fixtures/genie_checkpoint_v307ac4a: a small model with every shipped option (pointer, match input,
    rotary positions, step-mean actions) saved by the code of commit 307ac4a, whose config.json still lists the
    removed experiments' keys at their off values, with the logits that code computed for fixed inputs."""
    path = Path(__file__).parent / "fixtures" / "genie_checkpoint_v307ac4a"
    model = STMaskGIT.from_pretrained(path)
    expected = safetensors.torch.load_file(path / "expected_logits.safetensors")
    with torch.no_grad():
        logits = model.logits(expected["tokens"], expected["actions"])
    torch.testing.assert_close(logits, expected["logits"], atol=1e-6, rtol=1e-5)
    recipe = TrainingRecipe.from_pretrained(path / "config.json")
    assert recipe == TrainingRecipe(masking="whole_frames", max_corrupt_rate=0.05, self_reveal_ratio=0.5)
