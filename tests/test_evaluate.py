"""Challenge metrics (hand-computed values) and evaluate.py end to end on a tiny dataset and checkpoint."""
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from common.images import psnr
from data import RawTokenDataset, read_metadata, write_token_dataset
import evaluation.protocols
from common.cli import run_main
from tests.cli_runner import run_as_main
from evaluate import main
from genie import GenieConfig, STMaskGIT
from evaluation.protocols import (EvalConfig, FrameScorer, example_indices, rollout_result, score_rollout, teacher_forced_evaluate,
                              token_statistics)
from evaluation.metrics import RunningMean, images_to_unit_range, token_accuracy
from genie.metrics import factored_argmax_correct, factored_cross_entropy
from genie.inference import teacher_forced

REPO = Path(__file__).resolve().parents[1]
VOCAB = 64 ** 2
JSON_KEYS = {"loss", "acc", "copy_acc", "pred_lpips", "gen_time", "dec_time", "num_examples", "decoding"}
ROLLOUT_METRIC_KEYS = {f"{name}_{metric}{suffix}" for name in ("rollout", "hold")
                       for metric in ("psnr", "ssim", "lpips") for suffix in ("", "_mean")}
ROLLOUT_KEYS = ROLLOUT_METRIC_KEYS | {"protocol", "num_prompt_frames", "rollout_far_psnr", "hold_far_psnr",
                                     "gen_time", "num_examples", "maskgit_steps", "temperature", "copy_bias",
                                     "greedy_tokens", "stall_ratio", "unmask_mode"} | {
    f"{name}_{stat}{suffix}" for name in ("rollout", "true") for stat in ("unchanged", "repeated")
    for suffix in ("", "_mean")}


# ------------------------------------------------------------------ metric functions
def test_factored_cross_entropy_hand_values():
    logits = torch.zeros(1, 2, 2, 2)  # (B, V=2, F=2, tokens=2)
    logits[0, 0, 0, :] = math.log(3)  # factor 0: p(0) = 3/4, p(1) = 1/4; factor 1 uniform
    targets = torch.tensor([[3, 0]])  # 3 = f0 1 + 2 * f1 1;  0 = f0 0 + 2 * f1 0
    ce = factored_cross_entropy(logits, targets)
    expected = torch.tensor([[-math.log(1 / 4) - math.log(1 / 2), -math.log(3 / 4) - math.log(1 / 2)]])
    torch.testing.assert_close(ce, expected)
    assert factored_argmax_correct(logits, targets).tolist() == [[False, True]]


def test_uniform_logits_give_two_ln_512():
    ce = factored_cross_entropy(torch.zeros(2, 512, 2, 3), torch.randint(0, 2 ** 18, (2, 3)))
    torch.testing.assert_close(ce, torch.full((2, 3), 2 * math.log(512)))
    assert round(ce.mean().item(), 2) == 12.48


def test_cross_entropy_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="do not match targets"):
        factored_cross_entropy(torch.zeros(1, 4, 2, 3), torch.zeros(1, 4, dtype=torch.long))


def test_token_accuracy_and_running_mean():
    assert token_accuracy(torch.tensor([[1, 2], [3, 4]]), torch.tensor([[1, 0], [3, 4]])) == 0.75
    with pytest.raises(ValueError, match="differ in shape"):
        token_accuracy(torch.zeros(2), torch.zeros(3))
    mean = RunningMean()
    assert mean.mean is None
    mean.update(3.0, 2)
    mean.update(6.0, 1)
    assert mean.mean == 3.0


def test_psnr_is_one_function_for_uint8_and_unit_range_frames():
    a = torch.tensor([[[[0, 255, 128]]], [[[10, 20, 30]]]], dtype=torch.uint8)  # (2, 1, 1, 3)
    b = torch.tensor([[[[0, 255, 128]]], [[[10, 20, 81]]]], dtype=torch.uint8)
    db = psnr(a, b, (0.0, 255.0))
    assert db[0].item() == pytest.approx(100.0)  # identical images: the 1e-10 floor
    assert db[1].item() == pytest.approx(-10 * math.log10((51 / 255) ** 2 / 3), rel=1e-6)
    as_unit = [x.float() / 127.5 - 1 for x in (a, b)]
    torch.testing.assert_close(psnr(*as_unit, (-1.0, 1.0)), db, rtol=1e-5, atol=1e-4)
    # predictions are clamped to the range, as a decoder's outputs may overshoot it
    overshoot = as_unit[0] * 3
    torch.testing.assert_close(psnr(overshoot, overshoot.clamp(-1, 1), (-1.0, 1.0)), torch.full((2,), 100.0))


def test_images_to_unit_range():
    images = torch.zeros(1, 2, 2, 3, dtype=torch.uint8)
    images[0, 0, 1, 2] = 255
    images[0, 1, 0, 0] = 51
    x = images_to_unit_range(images)
    assert x.shape == (1, 3, 2, 2)
    assert x[0, 2, 0, 1] == 1.0 and x[0, 0, 1, 0] == pytest.approx(51 / 127.5 - 1) and x[0, 1, 1, 1] == -1.0


# ------------------------------------------------------------------ evaluate.py
def make_dataset(path: Path, s: int = 4, vocab: int = VOCAB, num_images: int = 120, seed: int = 0, **metadata):
    rng = np.random.default_rng(seed)
    video = rng.integers(0, vocab, size=(num_images, s, s))
    segment_ids = np.repeat(np.arange(3), -(-num_images // 3))[:num_images]
    write_token_dataset(path, video, segment_ids=segment_ids, metadata={"vocab_size": vocab, **metadata})
    return path


def make_checkpoint(path: Path, **overrides):
    kwargs = dict(num_layers=2, num_heads=4, d_model=32, T=8, S=16, image_vocab_size=VOCAB, num_prompt_frames=2)
    kwargs.update(overrides)
    torch.manual_seed(0)
    model = STMaskGIT(GenieConfig(**kwargs))
    model.init_weights()
    with torch.no_grad():
        model.out_x_proj.weight.normal_(0, 1.0)  # confident, position-dependent predictions
        model.pos_embed_TSC.normal_(0, 1.0)
    model.save_pretrained(path)
    return path


def eval_args(data, ckpt, *extra):
    return ["--val_data_dir", str(data), "--checkpoint_dir", str(ckpt), "--window_size", "8", "--stride", "3",
            "--batch_size", "3", "--device", "cpu", *extra]


def last_json_line(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


def run_evaluate(argv) -> int:
    """evaluate.py's exit status as the script ends (bad input: one error line, status 1)."""
    return run_main("evaluate.py", main, argv)


def error_line(err: str) -> str:
    """The last line of stderr, checked to be a one-line error with no traceback before it."""
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def make_tokenizer(path: Path) -> Path:
    """A random MAGVIT2 tokenizer decoding the 4x4 token frames of make_dataset to 32x32 images."""
    from magvit2 import VQConfig, VQModel
    torch.manual_seed(0)
    VQModel(VQConfig(z_channels=12, codebook_size=VOCAB, base_channels=32, ch_mult=[1, 1, 1, 1], num_res_blocks=1,
                     resolution=32)).save_pretrained(path)
    return path


def lpips_weights_available() -> bool:
    from magvit2.lpips import LPIPS, LPIPSWeightsNotFound
    try:
        LPIPS()
    except LPIPSWeightsNotFound:
        return False
    return True


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    return SimpleNamespace(data=make_dataset(root / "val"), ckpt=make_checkpoint(root / "ckpt"),
                           tokenizer=make_tokenizer(root / "tokenizer"), root=root)


def test_json_line_metrics_and_saved_outputs(tiny, capsys):
    out_dir = tiny.root / "outputs"
    assert main(eval_args(tiny.data, tiny.ckpt, "--skip_lpips", "--max_examples", "5", "--save_outputs_dir",
                          str(out_dir))) == 0
    result = last_json_line(capsys.readouterr().out)
    assert set(result) == JSON_KEYS
    assert result["num_examples"] == 5
    assert result["pred_lpips"] is None and result["dec_time"] is None
    assert result["gen_time"] > 0

    # CE of the first-step logits, recomputed here with the public model API (independent of the RNG)
    dataset = RawTokenDataset(tiny.data, window_size=8, stride=3, filter_overlaps=True)
    windows = torch.stack([dataset[i]["tokens"] for i in range(5)])
    assert windows.shape == (5, 8, 4, 4)
    model = STMaskGIT.from_pretrained(tiny.ckpt)
    _, logits = teacher_forced(model, windows, maskgit_steps=2)
    assert result["loss"] == pytest.approx(factored_cross_entropy(logits, windows[:, 1:]).mean().item(), rel=1e-5)

    # saved layout: per window frame 0 | predictions 1..7 | ground truth 1..7; acc matches the saved predictions
    meta = read_metadata(out_dir)
    assert (meta["num_prompt_frames"], meta["window_size"], meta["num_images"]) == (1, 8, 5 * 15)
    video = np.fromfile(out_dir / "video.bin", dtype=np.uint32).reshape(5, 15, 4, 4).astype(np.int64)
    assert np.array_equal(video[:, 0], windows[:, 0].numpy())
    assert np.array_equal(video[:, 8:], windows[:, 1:].numpy())
    assert (video[:, 1:8] < VOCAB).all()
    assert result["acc"] == pytest.approx((video[:, 1:8] == video[:, 8:]).mean())
    # copy_acc: copying ground-truth frame t-1, on the same windows
    assert result["copy_acc"] == pytest.approx((windows[:, :-1] == windows[:, 1:]).double().mean().item())
    assert RawTokenDataset(out_dir, window_size=15, stride=1, filter_overlaps=True).valid_start_inds.tolist() == \
        [15 * i for i in range(5)]


def test_spread_examples_cover_the_dataset_evenly(tiny, capsys):
    assert example_indices(10, None, True) == list(range(10))
    assert example_indices(10, 4, False) == [0, 1, 2, 3]
    assert example_indices(10, 4, True) == [0, 2, 5, 7]
    assert example_indices(10, 12, True) == list(range(10))
    # a video where each token stays put with a probability that grows along the video: copy_acc depends on
    # which windows are taken
    rng = np.random.default_rng(1)
    video = rng.integers(0, VOCAB, size=(120, 4, 4))
    for t in range(1, 120):
        stay = rng.random((4, 4)) < t / 120
        video[t][stay] = video[t - 1][stay]
    data = tiny.root / "drifting"
    write_token_dataset(data, video, segment_ids=np.zeros(120, dtype=np.int64), metadata={"vocab_size": VOCAB})
    dataset = RawTokenDataset(data, window_size=8, stride=3, filter_overlaps=True)
    copy_accs = []
    for spread in ([], ["--spread_examples"]):
        assert main(eval_args(data, tiny.ckpt, "--skip_lpips", "--max_examples", "3", *spread)) == 0
        result = last_json_line(capsys.readouterr().out)
        windows = torch.stack([dataset[i]["tokens"] for i in example_indices(len(dataset), 3, bool(spread))])
        assert result["num_examples"] == 3
        assert result["copy_acc"] == pytest.approx((windows[:, :-1] == windows[:, 1:]).double().mean().item())
        copy_accs.append(result["copy_acc"])
    assert copy_accs[1] > copy_accs[0] + 0.1  # the spread windows reach the later, stiller part of the video


class StubScorer:
    """Decodes token t to a flat image of value t % 256; distance = mean absolute pixel difference / 255."""

    def decode(self, tokens_NHW):
        return (tokens_NHW % 256).to(torch.uint8)[:, :, :, None].expand(-1, -1, -1, 3).repeat_interleave(8, 1)

    def lpips_distances(self, a, b):
        return (a.float() - b.float()).abs().mean(dim=(1, 2, 3)) / 255


def test_lpips_and_decode_time_with_a_stub_scorer(tiny):
    dataset = RawTokenDataset(tiny.data, window_size=8, stride=3, filter_overlaps=True)
    model = STMaskGIT.from_pretrained(tiny.ckpt)
    cfg = EvalConfig(val_data_dir=str(tiny.data), window_size=8, seed=0)
    outputs = []
    result = teacher_forced_evaluate(model, DataLoader(dataset, batch_size=4), cfg, torch.device("cpu"), StubScorer(),
                                     outputs)
    video = torch.from_numpy(np.concatenate(outputs))
    expected = ((video[:, 1:8] % 256) - (video[:, 8:] % 256)).abs().float().mean(dim=(2, 3)) / 255
    assert result["pred_lpips"] == pytest.approx(expected.mean().item(), rel=1e-5)
    assert result["dec_time"] > 0 and result["num_examples"] == len(dataset)


def test_real_tokenizer_and_lpips(tiny, capsys):
    if not lpips_weights_available():
        pytest.skip("no LPIPS weights on this machine (python -m magvit2.lpips_weights makes them)")
    assert main(eval_args(tiny.data, tiny.ckpt, "--max_examples", "2", "--tokenizer_ckpt", str(tiny.tokenizer))) == 0
    result = last_json_line(capsys.readouterr().out)
    assert result["pred_lpips"] >= 0 and result["dec_time"] > 0


def test_evaluate_script_runs_as_executable(tiny):
    env = {k: v for k, v in os.environ.items() if k != "WORLD_SIZE"}
    proc = subprocess.run([sys.executable, str(REPO / "evaluate.py"), *eval_args(tiny.data, tiny.ckpt),
                           "--skip_lpips", "--max_examples", "2"], capture_output=True, text=True, cwd=tiny.root,
                          env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = last_json_line(proc.stdout)
    assert set(result) == JSON_KEYS and result["num_examples"] == 2
    assert os.access(REPO / "evaluate.py", os.X_OK)
    assert (REPO / "evaluate.py").read_text().startswith("#!/usr/bin/env python")


@pytest.mark.parametrize("case, message", [
    ("grid", "tokens per frame"),
    ("vocab", "vocab_size 4096"),
    ("short_data", "needs 22 frames"),
    ("window_vs_T", "longer than the model's T"),
    ("no_checkpoint", "not found"),
    ("no_tokenizer", "--skip_lpips"),
    ("world_size", "single process"),
    ("copy_bias", "has no copy head"),
])
def test_bad_inputs_give_clear_errors(tiny, tmp_path, capsys, monkeypatch, case, message):
    data, ckpt, extra = tiny.data, tiny.ckpt, ["--skip_lpips"]
    if case == "grid":
        data = make_dataset(tmp_path / "val8", s=8)
    elif case == "vocab":
        ckpt = make_checkpoint(tmp_path / "ckpt", image_vocab_size=32 ** 2)
    elif case == "short_data":
        data = make_dataset(tmp_path / "short", num_images=12)
    elif case == "window_vs_T":
        ckpt = make_checkpoint(tmp_path / "ckpt", T=4)
    elif case == "no_checkpoint":
        ckpt = tmp_path / "missing" / "final_checkpt"
    elif case == "no_tokenizer":
        extra = ["--tokenizer_ckpt", str(tmp_path / "nope.ckpt")]
    elif case == "world_size":
        monkeypatch.setenv("WORLD_SIZE", "2")
    elif case == "copy_bias":
        extra += ["--copy_bias", "2"]
    assert run_evaluate(eval_args(data, ckpt, *extra)) == 1
    captured = capsys.readouterr()
    assert error_line(captured.err).startswith("evaluate.py: error: ") and message in error_line(captured.err)
    assert captured.out == ""


# ------------------------------------------------------------------ rollout protocol
class ImageStub(StubScorer):
    """StubScorer with 32x32 images (token t -> an 8x8 patch of value t % 256): SSIM needs 11x11."""

    def decode(self, tokens_NHW):
        return super().decode(tokens_NHW).repeat_interleave(8, 2)


def test_a_copying_model_scores_exactly_like_the_hold_baseline(tiny):
    rng = np.random.default_rng(0)
    last_NHW = torch.from_numpy(rng.integers(0, VOCAB, (3, 4, 4)))
    future_NhHW = torch.from_numpy(rng.integers(0, VOCAB, (3, 5, 4, 4)))
    copy_NhHW = last_NHW.unsqueeze(1).expand(-1, 5, -1, -1)
    scorers = [ImageStub()]
    if lpips_weights_available():
        scorers.append(FrameScorer(str(tiny.tokenizer), torch.device("cpu")))
    for scorer in scorers:
        scores = score_rollout(scorer, copy_NhHW, last_NHW, future_NhHW, with_lpips=True)
        assert set(scores) == {f"{n}_{m}" for n in ("rollout", "hold") for m in ("psnr", "ssim", "lpips")}
        for metric in ("psnr", "ssim", "lpips"):
            assert scores[f"rollout_{metric}"].shape == (3, 5)
            assert torch.equal(scores[f"rollout_{metric}"], scores[f"hold_{metric}"])
        result = rollout_result({k: v.double().sum(dim=0) for k, v in scores.items()}, 3, 8, 0.1)
        for key in ("psnr", "ssim", "lpips", "psnr_mean", "ssim_mean", "lpips_mean", "far_psnr"):
            assert result[f"rollout_{key}"] == result[f"hold_{key}"]


def test_rollout_scores_each_horizon_against_its_true_frame():
    stub = ImageStub()
    last_NHW = torch.full((2, 4, 4), 10)
    future_NhHW = torch.full((2, 3, 4, 4), 60)
    pred_NhHW = torch.full((2, 3, 4, 4), 35)
    pred_NhHW[:, 1] = 60  # horizon 2 is right
    future_NhHW[:, 2] = 10  # at horizon 3 the world came back to the prompt's last frame
    scores = score_rollout(stub, pred_NhHW, last_NHW, future_NhHW, with_lpips=False)
    assert set(scores) == {"rollout_psnr", "hold_psnr", "rollout_ssim", "hold_ssim"}
    psnr_25 = -10 * math.log10((25 / 255) ** 2)
    torch.testing.assert_close(scores["rollout_psnr"], torch.tensor([[psnr_25, 100.0, psnr_25]] * 2))
    torch.testing.assert_close(scores["hold_psnr"], torch.tensor([[-10 * math.log10((50 / 255) ** 2)] * 2 + [100.0]]
                                                                 * 2))
    assert scores["rollout_ssim"][0, 1] == pytest.approx(1.0) and scores["hold_ssim"][0, 2] == pytest.approx(1.0)
    assert scores["rollout_ssim"][0, 0] < 1.0


def test_token_statistics_show_a_frozen_and_a_flat_rollout():
    last_NHW = torch.arange(16).view(1, 4, 4)
    future_NhHW = torch.stack([last_NHW.roll(1, dims=-1), last_NHW.roll(2, dims=-1), last_NHW.roll(2, dims=-1)], 1)
    future_NhHW[0, 2, 0] = 99  # the last true frame: its first row flat and unchanged elsewhere
    frozen_NhHW = last_NHW.unsqueeze(1).expand(-1, 3, -1, -1)
    stats = token_statistics(frozen_NhHW, last_NHW, future_NhHW)
    torch.testing.assert_close(stats["rollout_unchanged"], torch.ones(1, 3))
    torch.testing.assert_close(stats["rollout_repeated"], torch.zeros(1, 3))
    torch.testing.assert_close(stats["true_unchanged"], torch.tensor([[0.0, 0.0, 12 / 16]]))
    torch.testing.assert_close(stats["true_repeated"], torch.tensor([[0.0, 0.0, 3 / 12]]))
    flat_NhHW = torch.full((1, 3, 4, 4), 98)
    flat_NhHW[0, 0, :, 0] = 97  # horizon 1: the first column differs from the rest
    stats = token_statistics(flat_NhHW, last_NHW, future_NhHW)
    torch.testing.assert_close(stats["rollout_repeated"], torch.tensor([[8 / 12, 1.0, 1.0]]))
    torch.testing.assert_close(stats["rollout_unchanged"], torch.tensor([[0.0, 12 / 16, 1.0]]))
    result = rollout_result({k: v.double().sum(dim=0) for k, v in stats.items()}, 1, 8, 0.1)
    assert result["rollout_repeated_mean"] == pytest.approx((8 / 12 + 2) / 3)


def test_rollout_protocol_json_line(tiny, capsys):
    assert main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "3",
                          "--max_examples", "4", "--tokenizer_ckpt", str(tiny.tokenizer), "--skip_lpips")) == 0
    result = last_json_line(capsys.readouterr().out)
    assert set(result) == ROLLOUT_KEYS
    assert (result["protocol"], result["num_prompt_frames"], result["num_examples"]) == ("rollout", 3, 4)
    for name in ("rollout", "hold"):
        assert len(result[f"{name}_psnr"]) == len(result[f"{name}_ssim"]) == 8 - 3
        assert result[f"{name}_lpips"] is None and result[f"{name}_lpips_mean"] is None
        assert result[f"{name}_far_psnr"] == result[f"{name}_psnr"][-1]
        assert result[f"{name}_psnr_mean"] == pytest.approx(np.mean(result[f"{name}_psnr"]))
        assert all(-1 <= v <= 1 for v in result[f"{name}_ssim"])
    assert result["gen_time"] > 0

    if not lpips_weights_available():
        return
    assert main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "3",
                          "--max_examples", "4", "--tokenizer_ckpt", str(tiny.tokenizer))) == 0
    with_lpips = last_json_line(capsys.readouterr().out)
    assert len(with_lpips["rollout_lpips"]) == len(with_lpips["hold_lpips"]) == 5
    assert with_lpips["rollout_lpips_mean"] >= 0
    assert with_lpips["rollout_psnr"] == result["rollout_psnr"]  # same seed, same frames
    assert with_lpips["hold_psnr"] == result["hold_psnr"]


@pytest.mark.parametrize("extra, message", [
    (["--protocol", "rollout", "--num_prompt_frames", "0"], "--num_prompt_frames must be in 1..7"),
    (["--protocol", "rollout", "--num_prompt_frames", "8"], "--num_prompt_frames must be in 1..7"),
    (["--num_prompt_frames", "3"], "--num_prompt_frames applies to --protocol rollout only"),
    (["--protocol", "rollout", "--num_prompt_frames", "3", "--save_outputs_dir", "out"],
     "does not apply to --protocol rollout"),
    (["--protocol", "copy_ceiling"], "invalid choice: 'copy_ceiling'"),  # python diagnose.py copy_ceiling
    (["--per_window_out", "windows.jsonl"], "unrecognized arguments: --per_window_out"),  # diagnostics per_window
    (["--withhold_actions"], "unrecognized arguments: --withhold_actions"),  # diagnostics withheld_actions
    (["--greedy_tokens", "factored"], "invalid choice: 'factored'"),
    (["--maskgit_steps", "0"], "--maskgit_steps must be >= 1, got 0"),
    (["--temperature=-1"], "--temperature must be >= 0, got -1.0"),
])
def test_bad_flags_are_usage_errors(tiny, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_info:
        main(eval_args(tiny.data, tiny.ckpt, *extra))
    assert exit_info.value.code == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith("evaluate.py: error: ") and message in line


def test_rollout_needs_a_tokenizer_even_with_skip_lpips(tiny, tmp_path, capsys):
    assert run_evaluate(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "3",
                                  "--skip_lpips", "--tokenizer_ckpt", str(tmp_path / "nope.ckpt"))) == 1
    captured = capsys.readouterr()
    assert "decodes frames for PSNR and SSIM" in error_line(captured.err) and captured.out == ""


@pytest.mark.parametrize("choice, expected", [(None, "joint"), ("joint", "joint"),
                                              ("best_neighbour", "best_neighbour")])
def test_greedy_tokens_sets_the_models_decoding(tiny, capsys, monkeypatch, choice, expected):
    settings = []
    real = STMaskGIT.set_decoding
    monkeypatch.setattr(STMaskGIT, "set_decoding",
                        lambda model, value: settings.append(value.greedy_tokens) or real(model, value))
    flag = () if choice is None else ("--greedy_tokens", choice)
    assert main(eval_args(tiny.data, tiny.ckpt, "--skip_lpips", "--max_examples", "1", *flag)) == 0
    assert settings[-1] == expected
    assert last_json_line(capsys.readouterr().out)["decoding"]["greedy_tokens"] == expected


def test_the_checkpoints_decoding_is_used_unless_a_flag_overrides_it(tiny, tmp_path, capsys, monkeypatch):
    """A checkpoint's decoding.json decides how its futures are sampled; a flag overrides one value; the JSON line
    says what was used; the teacher-forced protocol scores the same checkpoint greedily with its MaskGIT steps."""
    ckpt = tmp_path / "ckpt"
    shutil.copytree(tiny.ckpt, ckpt)
    (ckpt / "decoding.json").write_text(json.dumps({"temperature": 1.0, "maskgit_steps": 1, "unmask_mode": "greedy"}))
    seen = []
    real = evaluation.protocols.generate_frames
    monkeypatch.setattr(evaluation.protocols, "generate_frames",
                        lambda *a, **kw: seen.append((kw["temperature"], kw["maskgit_steps"])) or real(*a, **kw))
    rollout = ("--protocol", "rollout", "--num_prompt_frames", "3", "--max_examples", "2", "--tokenizer_ckpt",
               str(tiny.tokenizer), "--skip_lpips")
    assert main(eval_args(tiny.data, ckpt, *rollout)) == 0
    result = last_json_line(capsys.readouterr().out)
    assert seen == [(1.0, 1)] and (result["temperature"], result["maskgit_steps"], result["unmask_mode"]) == \
        (1.0, 1, "greedy")
    assert main(eval_args(tiny.data, ckpt, *rollout, "--temperature", "0")) == 0
    assert seen[-1] == (0.0, 1) and last_json_line(capsys.readouterr().out)["temperature"] == 0.0
    assert main(eval_args(tiny.data, ckpt, "--skip_lpips", "--max_examples", "1")) == 0
    decoding = last_json_line(capsys.readouterr().out)["decoding"]
    assert (decoding["temperature"], decoding["maskgit_steps"], decoding["unmask_mode"]) == (0.0, 1, "greedy")
    (ckpt / "decoding.json").write_text(json.dumps({"temperature": -1}))
    assert run_evaluate(eval_args(tiny.data, ckpt, "--skip_lpips")) == 1
    assert "temperature must be >= 0, got -1" in error_line(capsys.readouterr().err)


def test_stall_ratio_reaches_the_rollouts_and_the_json_line(tiny, capsys, monkeypatch):
    seen = []
    real = evaluation.protocols.generate_frames
    monkeypatch.setattr(evaluation.protocols, "generate_frames",
                        lambda *a, **kw: seen.append(kw["stall_ratio"]) or real(*a, **kw))
    assert main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "3", "--max_examples",
                          "2", "--tokenizer_ckpt", str(tiny.tokenizer), "--skip_lpips", "--stall_ratio", "1")) == 0
    assert seen == [1.0] and last_json_line(capsys.readouterr().out)["stall_ratio"] == 1.0
    with pytest.raises(SystemExit):
        main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--stall_ratio", "-0.1"))
    assert "expected a number in (0, 1], got -0.1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "1", "--stall_ratio", "1"))
    assert "needs --num_prompt_frames >= 2, got 1" in capsys.readouterr().err


def test_bad_input_ends_the_script_in_one_line(tiny, tmp_path):
    """As a script: a usage error (exit status 2) and a missing dataset (1) end in one error line, no traceback."""
    env = {k: v for k, v in os.environ.items() if k != "WORLD_SIZE"}
    cases = [(["--stall_ratio", "2"], 2, "evaluate.py: error: argument --stall_ratio: expected a number in (0, 1]"),
             (["--val_data_dir", str(tmp_path / "missing")], 1, f"evaluate.py: error: {tmp_path / 'missing'}")]
    # the later --val_data_dir wins
    ran = run_as_main({i: (REPO / "evaluate.py", eval_args(tiny.data, tiny.ckpt, "--skip_lpips") + extra)
                       for i, (extra, _, _) in enumerate(cases)}, cwd=tiny.root, env=env)
    for i, (extra, code, message) in enumerate(cases):
        proc = ran[i]
        assert proc.returncode == code and proc.stdout == ""
        assert error_line(proc.stderr).startswith(message), proc.stderr
