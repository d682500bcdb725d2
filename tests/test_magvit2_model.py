"""MAGVIT2 tokenizer: config, published architecture and names, DCR depth-to-space, checkpoint loading."""
import json
import os

import numpy as np
import pytest
import torch
import torch.nn as nn

from common.config import ConfigError
from magvit2 import CheckpointError, VQConfig, VQModel
from magvit2.modules import Upsampler, depth_to_space


def tiny_config(**overrides) -> VQConfig:
    fields = dict(base_channels=32, ch_mult=[1, 2], num_res_blocks=1, z_channels=6, codebook_size=64,
                  resolution=16)
    return VQConfig(**{**fields, **overrides})


def randomize(model: nn.Module, seed: int) -> nn.Module:
    """Random weights everywhere (GroupNorm affine included), so swapped or misplaced weights change outputs."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * (0.2 if p.ndim > 1 else 0.5) + (1.0 if p.ndim == 1 else 0))
    return model


# ---------------------------------------------------------------- config

def test_config_defaults_are_the_1x_tokenizer_and_round_trip_json(tmp_path):
    c = VQConfig()
    assert (c.in_channels, c.z_channels, c.base_channels, c.ch_mult, c.num_res_blocks, c.codebook_size) == \
        (3, 18, 128, [1, 1, 2, 2, 4], 2, 2 ** 18)
    assert c.latent_size(256) == 16 and c.downsample_factor == 16
    custom = tiny_config(entropy_weight=0.5, disc_start=100)
    custom.save(tmp_path / "c.json")
    assert VQConfig.from_pretrained(tmp_path / "c.json") == custom
    assert VQConfig.from_dict(json.loads(json.dumps(custom.to_dict()))) == custom


def test_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="unknown key"):
        VQConfig.from_dict({"z_channel": 18}, source="cfg.json")
    with pytest.raises(ConfigError, match="codebook_size"):
        VQConfig(z_channels=10)
    with pytest.raises(ConfigError, match="codebook_size"):  # rejected without computing 2 ** z_channels
        VQConfig(z_channels=2 ** 70)
    with pytest.raises(ConfigError, match="codebook_size"):
        VQConfig(codebook_size=2 ** 18 + 1)
    with pytest.raises(ConfigError, match="divisible by 32"):
        VQConfig(base_channels=16)
    with pytest.raises(ValueError, match="divisible"):
        VQConfig().latent_size(100)


# ---------------------------------------------------------------- architecture

def test_published_parameter_counts_and_names():
    model = VQModel()
    # docs/formats.md §4: encoder 25.0 M, decoder 40.5 M parameters
    assert round(sum(p.numel() for p in model.encoder.parameters()) / 1e6, 1) == 25.0
    assert round(sum(p.numel() for p in model.decoder.parameters()) / 1e6, 1) == 40.5
    sd = model.state_dict()
    for name, shape in [("encoder.conv_in.weight", (128, 3, 3, 3)),
                        ("encoder.down.0.block.0.conv1.weight", (128, 128, 3, 3)),
                        ("encoder.down.0.block.1.norm2.bias", (128,)),
                        ("encoder.down.0.downsample.weight", (128, 128, 3, 3)),
                        ("encoder.down.0.downsample.bias", (128,)),
                        ("encoder.down.2.block.0.nin_shortcut.weight", (256, 128, 1, 1)),
                        ("encoder.mid_block.1.conv2.weight", (512, 512, 3, 3)),
                        ("encoder.norm_out.weight", (512,)),
                        ("encoder.conv_out.weight", (18, 512, 1, 1)),
                        ("encoder.conv_out.bias", (18,)),
                        ("decoder.conv_in.weight", (512, 18, 3, 3)),
                        ("decoder.conv_in.bias", (512,)),
                        ("decoder.mid_block.0.norm1.weight", (512,)),
                        ("decoder.up.4.upsample.conv1.weight", (2048, 512, 3, 3)),
                        ("decoder.up.3.block.0.nin_shortcut.weight", (256, 512, 1, 1)),
                        ("decoder.up.1.upsample.conv1.bias", (512,)),
                        ("decoder.conv_out.weight", (3, 128, 3, 3))]:
        assert tuple(sd[name].shape) == shape, name
    absent = ["encoder.conv_in.bias", "encoder.down.0.block.0.conv1.bias", "encoder.down.4.downsample.weight",
              "decoder.up.0.upsample.conv1.weight", "encoder.down.0.block.0.nin_shortcut.weight"]
    assert not set(absent) & set(sd)
    assert not any(k.startswith("quantizer.") for k in sd)  # the LFQ has no weights or buffers


@pytest.mark.parametrize("ch_mult,sizes", [([1, 2], [(8, 8), (16, 24)]), ([1, 1, 2], [(8, 8), (16, 24)])])
def test_encoder_decoder_shapes(ch_mult, sizes):
    model = VQModel(tiny_config(ch_mult=ch_mult)).eval()
    f = 2 ** (len(ch_mult) - 1)
    for h, w in sizes:
        x = torch.rand(2, 3, h, w) * 2 - 1
        z = model.encode(x)
        assert z.shape == (2, 6, h // f, w // f)
        x_rec, q = model(x)
        assert x_rec.shape == x.shape and q.token_ids.shape == (2, h // f, w // f)


def test_depth_to_space_is_dcr_not_pixel_shuffle():
    B, C, H, W, b = 2, 3, 4, 5, 2
    x = torch.randn(B, C * b * b, H, W)
    y = depth_to_space(x, b)
    assert y.shape == (B, C, H * b, W * b)
    # DCR: input channel (i * b + j) * C + c lands on output channel c at pixel (h * b + i, w * b + j)
    expected = torch.empty_like(y)
    for i in range(b):
        for j in range(b):
            for c in range(C):
                expected[:, c, i::b, j::b] = x[:, (i * b + j) * C + c]
    assert torch.equal(y, expected)
    assert not torch.equal(y, nn.PixelShuffle(b)(x))  # CRD order: channel c * b^2 + i * b + j


def test_upsampler_uses_dcr():
    up = Upsampler(32)
    x = torch.randn(1, 32, 3, 3)
    assert torch.equal(up(x), depth_to_space(up.conv1(x), 2))


# ---------------------------------------------------------------- tokens <-> images

def test_images_tokens_images():
    model = randomize(VQModel(tiny_config()), 0).eval()
    images = np.random.default_rng(0).integers(0, 256, (5, 16, 16, 3), dtype=np.uint8)
    tokens = model.images_to_tokens(images, batch_size=2)
    assert tokens.shape == (5, 8, 8) and tokens.dtype == np.int64 and tokens.min() >= 0 and tokens.max() < 64
    with torch.no_grad():
        z = model.encode(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 127.5 - 1)
    assert np.array_equal(tokens, model.quantize(z).token_ids.numpy())
    pixels = model.tokens_to_images(tokens.astype(np.uint32), batch_size=3)
    with torch.no_grad():
        x = model.decode(model.quantize(z).zq)
    assert pixels.shape == (5, 16, 16, 3) and pixels.dtype == np.uint8
    assert np.array_equal(pixels, ((x + 1) * 127.5).clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy())
    as_tensor = model.tokens_to_images(torch.from_numpy(tokens))
    assert isinstance(as_tensor, torch.Tensor) and np.array_equal(as_tensor.numpy(), pixels)


def test_bad_images_and_tokens_are_rejected():
    model = VQModel(tiny_config()).eval()
    with pytest.raises(TypeError, match="uint8"):
        model.images_to_tokens(np.zeros((1, 16, 16, 3), np.float32))
    with pytest.raises(ValueError, match="divisible"):
        model.images_to_tokens(np.zeros((1, 15, 16, 3), np.uint8))
    with pytest.raises(ValueError, match=r"\[0, 64\)"):
        model.tokens_to_images(np.full((1, 4, 4), 64))


# ---------------------------------------------------------------- checkpoints

def write_lightning_ckpt(path, raw: VQModel, ema: VQModel, extra=None):
    """The Open-MAGVIT2 / Lightning layout: raw weights, loss.* weights, dot-less model_ema.* copies."""
    state_dict = dict(raw.state_dict())
    state_dict["loss.discriminator.main.0.weight"] = torch.randn(64, 3, 4, 4)
    state_dict["loss.perceptual_loss.lin0.model.1.weight"] = torch.randn(1, 64, 1, 1)
    for name, value in ema.state_dict().items():
        state_dict["model_ema." + name.replace(".", "")] = value.clone()
    state_dict["model_ema.lossdiscriminatormain0weight"] = torch.randn(64, 3, 4, 4)
    state_dict["model_ema.decay"] = torch.tensor(0.999)
    state_dict["model_ema.num_updates"] = torch.tensor(1234, dtype=torch.int32)
    torch.save({"epoch": 3, "global_step": 1000, "state_dict": state_dict, **(extra or {})}, path)


def decode_some(model: VQModel) -> np.ndarray:
    tokens = np.arange(2 * 4 * 4).reshape(2, 4, 4) * 7 % model.config.codebook_size
    return model.tokens_to_images(tokens)


def test_lightning_checkpoint_loads_ema_or_raw_weights(tmp_path):
    cfg = tiny_config()
    raw, ema = randomize(VQModel(cfg), 1).eval(), randomize(VQModel(cfg), 2).eval()
    path = tmp_path / "magvit2.ckpt"
    write_lightning_ckpt(path, raw, ema)
    loaded = VQModel.from_checkpoint(path).eval()  # config inferred from the weight shapes
    assert (loaded.config.z_channels, loaded.config.base_channels, loaded.config.ch_mult,
            loaded.config.num_res_blocks) == (6, 32, [1, 2], 1)
    assert np.array_equal(decode_some(loaded), decode_some(ema))
    assert not np.array_equal(decode_some(loaded), decode_some(raw))
    loaded_raw = VQModel.from_checkpoint(path, config=cfg, use_ema=False).eval()
    assert np.array_equal(decode_some(loaded_raw), decode_some(raw))
    for name, value in ema.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name


def test_mismatched_checkpoint_lists_keys(tmp_path):
    cfg = tiny_config()
    model = randomize(VQModel(cfg), 1)
    path = tmp_path / "magvit2.ckpt"
    write_lightning_ckpt(path, model, model)
    with pytest.raises(CheckpointError) as info:
        VQModel.from_checkpoint(path, config=tiny_config(ch_mult=[1, 2, 2], z_channels=8, codebook_size=256))
    message = str(info.value)
    assert "missing keys" in message and "encoder.down.2.block.0.conv1.weight" in message
    assert "shape mismatches" in message and "encoder.conv_out.weight" in message
    assert str(path) in message
    with pytest.raises(CheckpointError, match="unexpected keys.*decoder.up.1"):
        VQModel.from_checkpoint(path, config=tiny_config(ch_mult=[1]))


def test_malicious_pickle_is_refused(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    cfg = tiny_config()
    model = VQModel(cfg)
    path = tmp_path / "evil.ckpt"
    write_lightning_ckpt(path, model, model, extra={"callbacks": Evil()})
    with pytest.raises(CheckpointError, match="references code.*allow_unsafe_pickle"):
        VQModel.from_checkpoint(path)
    assert not marker.exists()


def test_unsafe_pickle_needs_explicit_opt_in(tmp_path):
    import argparse  # Lightning stores hyper-parameters as objects like this one

    cfg = tiny_config()
    model = randomize(VQModel(cfg), 3).eval()
    path = tmp_path / "hparams.ckpt"
    write_lightning_ckpt(path, model, model, extra={"hyper_parameters": argparse.Namespace(lr=1e-4)})
    with pytest.raises(CheckpointError, match="--allow_unsafe_pickle"):
        VQModel.from_checkpoint(path)
    loaded = VQModel.from_checkpoint(path, allow_unsafe_pickle=True).eval()
    assert np.array_equal(decode_some(loaded), decode_some(model))


def test_unreadable_and_missing_checkpoints(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.ckpt"):
        VQModel.from_checkpoint(tmp_path / "nowhere.ckpt")
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"definitely not a checkpoint")
    with pytest.raises(CheckpointError, match="garbage.ckpt"):
        VQModel.from_checkpoint(garbage)
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        (tmp_path / "empty_dir").mkdir()
        VQModel.from_checkpoint(tmp_path / "empty_dir")


def test_save_pretrained_round_trip(tmp_path):
    model = randomize(VQModel(tiny_config(entropy_weight=0.3)), 4).eval()
    out = tmp_path / "tok"
    model.save_pretrained(out)
    assert sorted(p.name for p in out.iterdir()) == ["MANIFEST.json", "config.json", "model.safetensors"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tok"]  # no temp dirs left behind
    loaded = VQModel.from_checkpoint(out).eval()
    assert loaded.config == model.config
    assert np.array_equal(decode_some(loaded), decode_some(model))
    # saving again into the existing directory replaces the files and keeps other files there
    (out / "training_state").mkdir()
    other = randomize(VQModel(tiny_config(entropy_weight=0.3)), 5).eval()
    other.save_pretrained(out)
    assert (out / "training_state").is_dir()
    assert np.array_equal(decode_some(VQModel.from_checkpoint(out).eval()), decode_some(other))


def test_shipped_tokenizer_tokens_do_not_depend_on_the_batch():
    """build_sample encodes in batches of 8 for speed: the tokens must be those of the former batches of 256."""
    from sample_world.build import SHIPPED_TOKENIZER, resolve_tokenizer

    model = VQModel.from_checkpoint(resolve_tokenizer(SHIPPED_TOKENIZER)).eval()
    rng = np.random.default_rng(0)
    smooth = np.repeat(np.repeat(rng.integers(0, 256, (270, 8, 8, 3), dtype=np.uint8), 8, axis=1), 8, axis=2)
    images = np.concatenate([smooth, rng.integers(0, 256, (30, 64, 64, 3), dtype=np.uint8)])
    by_256 = model.images_to_tokens(images, batch_size=256)
    assert len(np.unique(by_256)) > 100  # varied codes, so a batch-dependent encoder would show
    assert np.array_equal(model.images_to_tokens(images, batch_size=8), by_256)
