"""Tokenizer training: losses, frame loading, a short run that learns, exact resume, the GAN path, the CLI."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import load_file, save_file

from common.train_state import TrainingStateError
from magvit2.config import VQConfig
from magvit2.lfq import LFQOutput
from magvit2.lpips import expected_shapes
from magvit2.losses import (LeCAM, NLayerDiscriminator, VQLoss, adaptive_generator_weight, hinge_d_loss,
                            non_saturating_d_loss)
from magvit2.model import VQModel
from magvit2.train import FrameDataset, FrameDataError, codebook_usage, load_frame_array, main, parse_args, run

REPO = Path(__file__).resolve().parents[1]
TINY = ["--base_channels", "32", "--ch_mult", "1", "1", "--num_res_blocks", "1", "--z_channels", "4"]


def smooth_frames(n: int, size: int, seed: int = 0) -> np.ndarray:
    """Random-but-structured frames: oriented sinusoidal gradients with random phase and colour mix."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    frames = []
    for _ in range(n):
        angle, phase, mix = rng.uniform(0, 2 * np.pi, 3)
        wave = np.sin(2 * np.pi * (xx * np.cos(angle) + yy * np.sin(angle)) + phase)
        image = np.stack([wave, np.cos(mix) * wave, 2 * yy - 1], axis=-1)
        frames.append(((image + 1) * 127.5).clip(0, 255).astype(np.uint8))
    return np.stack(frames)


@pytest.fixture
def frames_npz(tmp_path) -> Path:
    path = tmp_path / "frames.npz"
    np.savez(path, frames=smooth_frames(16, 16))
    return path


def _args(data, out, *extra):
    return parse_args(["--train_data", str(data), "--output_dir", str(out), "--resolution", "16", "--no_lpips",
                       "--batch_size", "4", "--learning_rate", "3e-3", "--log_every", "1", *TINY, *map(str, extra)])


def _log(out: Path) -> list:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


# ---------------------------------------------------------------- losses

def test_adaptive_weight_is_the_grad_norm_ratio():
    layer = torch.nn.Linear(3, 2, bias=False)
    out = layer(torch.randn(5, 3))
    rec, gan = out.pow(2).mean(), 3.0 * out[:, 0].mean()
    w_rec = torch.autograd.grad(rec, layer.weight, retain_graph=True)[0]
    w_gan = torch.autograd.grad(gan, layer.weight, retain_graph=True)[0]
    expected = 0.8 * w_rec.norm() / (w_gan.norm() + 1e-4)
    torch.testing.assert_close(adaptive_generator_weight(rec, gan, layer.weight, disc_weight=0.8), expected)


def test_gan_losses_reward_a_correct_discriminator():
    sure_real, sure_fake = torch.full((2, 1, 3, 3), 8.0), torch.full((2, 1, 3, 3), -8.0)
    for loss in (hinge_d_loss, non_saturating_d_loss):
        assert loss(sure_real, sure_fake) < 0.01
        assert loss(sure_fake, sure_real) > 2.0


def test_lecam_tracks_logit_emas_and_penalizes_drift():
    lecam = LeCAM(decay=0.5)
    real, fake = torch.full((4, 1, 2, 2), 2.0), torch.full((4, 1, 2, 2), -2.0)
    lecam.update(real, fake)
    assert lecam.ema_real.item() == pytest.approx(1.0) and lecam.ema_fake.item() == pytest.approx(-1.0)
    # relu(2 - (-1))^2 + relu(1 - (-2))^2
    assert lecam(real, fake).item() == pytest.approx(18.0)
    assert lecam(torch.full_like(real, -1.0), torch.full_like(fake, 1.0)).item() == 0.0


def test_vqloss_gan_switches_on_at_disc_start():
    config = VQConfig(base_channels=32, ch_mult=[1, 1], num_res_blocks=1, z_channels=4, codebook_size=16,
                      resolution=16, disc_start=2)
    model = VQModel(config).train()
    loss_fn = VQLoss(config, perceptual=None, use_gan=True, gan_loss="non_saturating", disc_channels=8, disc_layers=1)
    x = torch.rand(2, 3, 16, 16) * 2 - 1
    x_rec, quant = model(x)
    assert isinstance(quant, LFQOutput)
    before, logs_before = loss_fn.generator_loss(x, x_rec, quant, step=1, last_layer=model.decoder.conv_out.weight)
    after, logs_after = loss_fn.generator_loss(x, x_rec, quant, step=2, last_layer=model.decoder.conv_out.weight)
    assert "g_loss" not in logs_before and "g_loss" in logs_after
    assert after.item() != pytest.approx(before.item())
    after.backward()
    assert all(p.grad is None for p in loss_fn.discriminator.parameters())  # the generator step leaves D alone
    with pytest.raises(RuntimeError, match="disc_start"):
        loss_fn.discriminator_loss(x, x_rec, step=1)
    d_loss, d_logs = loss_fn.discriminator_loss(x, x_rec, step=2)
    d_loss.backward()
    assert "lecam" in d_logs and all(p.grad is not None for p in loss_fn.discriminator.parameters())


def test_patch_discriminator_shapes():
    disc = NLayerDiscriminator(3, base_channels=8, num_layers=3)
    assert disc(torch.zeros(2, 3, 64, 64)).shape == (2, 1, 6, 6)
    assert disc(torch.zeros(1, 3, 24, 24)).shape == (1, 1, 1, 1)
    with pytest.raises(ValueError, match="at least 24x24"):
        disc(torch.zeros(1, 3, 16, 16))


def test_codebook_usage_counts_and_perplexity():
    usage = codebook_usage(torch.tensor([0, 0, 1, 1, 2, 2, 3, 3]), codebook_size=16)
    assert usage["codes_used"] == 4 and usage["codebook_usage"] == 0.25
    assert usage["perplexity"] == pytest.approx(4.0)


# ---------------------------------------------------------------- frames

def test_frame_sources(tmp_path):
    frames = smooth_frames(6, 16)
    np.savez(tmp_path / "plain.npz", frames=frames)
    np.savez_compressed(tmp_path / "packed.npz", frames=frames[:2])
    memmapped, packed = load_frame_array(tmp_path / "plain.npz"), load_frame_array(tmp_path / "packed.npz")
    assert isinstance(memmapped, np.memmap)
    np.testing.assert_array_equal(memmapped, frames)
    np.testing.assert_array_equal(packed, frames[:2])

    images = tmp_path / "images"
    images.mkdir()
    Image.fromarray(np.zeros((20, 30, 3), np.uint8)).save(images / "wide.png")  # center-cropped, then resized
    dataset = FrameDataset([str(tmp_path / "*.npz"), str(images)], resolution=16)
    assert len(dataset) == 6 + 2 + 1
    assert dataset[7].shape == (3, 16, 16) and dataset[7].dtype == torch.uint8
    np.testing.assert_array_equal(dataset[0].permute(1, 2, 0).numpy(), frames[2 - 2])  # packed.npz sorts first
    assert dataset[8].shape == (3, 16, 16)


def test_bad_frame_sources_are_clear_errors(tmp_path):
    np.savez(tmp_path / "wrong_key.npz", images=np.zeros((2, 8, 8, 3), np.uint8))
    np.savez(tmp_path / "wrong_dtype.npz", frames=np.zeros((2, 8, 8, 3), np.float32))
    with pytest.raises(FrameDataError, match="wrong_key.npz.*'frames'"):
        load_frame_array(tmp_path / "wrong_key.npz")
    with pytest.raises(FrameDataError, match="wrong_dtype.npz.*uint8"):
        load_frame_array(tmp_path / "wrong_dtype.npz")
    with pytest.raises(FrameDataError, match="missing.npz: no such file"):
        main(["--train_data", str(tmp_path / "missing.npz"), "--output_dir", str(tmp_path / "out"), "--no_lpips"])


# ---------------------------------------------------------------- training runs

def test_short_run_learns_and_exports_a_loadable_tokenizer(frames_npz, tmp_path):
    out = tmp_path / "run"
    results = run(_args(frames_npz, out, "--max_train_steps", "20", "--checkpointing_steps", "0",
                        "--eval_every_n_steps", "0", "--ema_decay", "0.9"))
    l1 = [entry["l1"] for entry in _log(out) if "l1" in entry]
    assert len(l1) == 20
    assert np.mean(l1[-5:]) < 0.8 * np.mean(l1[:5])  # typically 0.6-0.7 after 20 steps
    assert results["val_psnr"] > 12 and 0 < results["val_codebook_usage"] <= 1
    assert json.loads((out / "eval_results.json").read_text())["step"] == 20
    tokenizer = VQModel.from_checkpoint(out / "final_checkpt")
    assert tokenizer.config.z_channels == 4
    tokens = tokenizer.images_to_tokens(smooth_frames(2, 16, seed=9))
    assert tokens.shape == (2, 8, 8) and tokens.max() < 16  # one stride-2 level


def test_resume_takes_the_same_steps_as_an_uninterrupted_run(tmp_path):
    data = tmp_path / "frames.npz"
    np.savez(data, frames=smooth_frames(24, 16))
    common = ["--use_gan", "--disc_layers", "1", "--disc_start", "2", "--augment", "--checkpointing_steps", "2",
              "--eval_every_n_steps", "0", "--max_eval_frames", "4"]
    full, split = tmp_path / "full", tmp_path / "split"
    run(_args(data, full, *common, "--max_train_steps", "4"))
    run(_args(data, split, *common, "--max_train_steps", "2"))
    assert (split / "checkpoint-2" / "gan.safetensors").is_file()
    run(_args(data, split, *common, "--max_train_steps", "4", "--resume_from_checkpoint", "latest"))
    for name in ("raw_model.safetensors", "model.safetensors", "gan.safetensors"):
        a, b = load_file(str(full / "checkpoint-4" / name)), load_file(str(split / "checkpoint-4" / name))
        assert a.keys() == b.keys()
        for key in a:
            assert torch.equal(a[key], b[key]), f"{name}:{key} differs after resume"
    gan_logs = [entry for entry in _log(split) if "d_loss" in entry]
    assert gan_logs and all(np.isfinite(entry["g_weight"]) for entry in gan_logs)


def test_gan_non_saturating_fixed_weight_with_lpips(tmp_path):
    data = tmp_path / "frames32.npz"
    np.savez(data, frames=smooth_frames(12, 32))
    out = tmp_path / "gan"
    weights = tmp_path / "lpips.safetensors"
    save_file({k: 0.05 * torch.randn(shape).abs() for k, shape in expected_shapes().items()}, str(weights))
    args = _args(data, out, "--resolution", "32", "--use_gan", "--disc_layers", "2", "--disc_start", "0",
                 "--gan_loss", "non_saturating", "--gan_weighting", "fixed", "--max_train_steps", "2",
                 "--checkpointing_steps", "0", "--max_eval_frames", "2")
    args.no_lpips, args.lpips_weights = False, str(weights)
    results = run(args)
    logs = [entry for entry in _log(out) if "d_loss" in entry]
    assert len(logs) == 2 and all(entry["g_weight"] == pytest.approx(VQConfig().gen_loss_weight) for entry in logs)
    assert all("lpips" in entry for entry in logs) and "val_lpips" in results


def test_resume_refuses_a_different_architecture(frames_npz, tmp_path):
    out = tmp_path / "run"
    run(_args(frames_npz, out, "--max_train_steps", "1", "--checkpointing_steps", "1"))
    with pytest.raises(TrainingStateError, match="different tokenizer config"):
        main(["--train_data", str(frames_npz), "--output_dir", str(out), "--resolution", "16", "--no_lpips",
              "--batch_size", "4", "--resume_from_checkpoint", "latest", "--max_train_steps", "2",
              "--base_channels", "32", "--ch_mult", "1", "1", "--num_res_blocks", "2", "--z_channels", "4"])


@pytest.mark.parametrize("entry", [["-m", "magvit2.train"], [str(REPO / "magvit2" / "train.py")]])
def test_cli_entry_points(entry):
    result = subprocess.run([sys.executable, *entry, "--help"], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stderr[-2000:]
    for flag in ("--train_data", "--resume_from_checkpoint", "--perceptual_every", "--no_lpips", "--use_gan"):
        assert flag in result.stdout
