"""python -m magvit2.score: a tokenizer's reconstructions scored against the real frames."""
import json

import numpy as np
import pytest

from tests.cli_runner import run_as_main
from tests.play_fixtures import tiny_tokenizer
from tests.test_evaluate import lpips_weights_available


def test_score_reports_each_file_and_all_of_them(tmp_path):
    if not lpips_weights_available():
        pytest.skip("no LPIPS weights on this machine (python -m magvit2.lpips_weights makes them)")
    tokenizer = tiny_tokenizer(tmp_path / "tokenizer")
    rng = np.random.default_rng(0)
    still = np.repeat(rng.integers(0, 256, size=(1, 64, 64, 3), dtype=np.uint8), 40, axis=0)  # one walk, no motion
    noisy = rng.integers(0, 256, size=(40, 64, 64, 3), dtype=np.uint8)
    np.savez(tmp_path / "still.npz", frames=still, segment_ids=np.zeros(40, dtype=np.int32))
    np.savez(tmp_path / "noisy.npz", frames=noisy, segment_ids=np.arange(40, dtype=np.int32) // 20)
    argv = ["--tokenizer_ckpt", tokenizer, "--frames", tmp_path / "still.npz", tmp_path / "noisy.npz",
            "--stride", "5", "--device", "cpu", "--num_threads", "1"]
    proc = run_as_main({"score": ("magvit2.score", argv)})["score"]
    assert proc.returncode == 0, proc.stderr[-2000:]
    still_line, noisy_line, all_line = (json.loads(line) for line in proc.stdout.strip().splitlines())
    assert still_line["frames"] == noisy_line["frames"] == 8 and all_line["frames"] == 16
    assert still_line["tokens_unchanged"] == 1.0  # the same frame gives the same tokens
    assert noisy_line["tokens_unchanged"] < 0.5
    assert still_line["codes_used"] < noisy_line["codes_used"]
    for line in (still_line, noisy_line, all_line):
        assert np.isfinite([line["psnr"], line["lpips"], line["sharpness"], line["kid_x1000"]]).all()


def test_score_names_a_file_without_frames(tmp_path):
    tokenizer = tiny_tokenizer(tmp_path / "tokenizer")
    np.savez(tmp_path / "bad.npz", images=np.zeros((2, 64, 64, 3), dtype=np.uint8))
    procs = run_as_main({"bad": ("magvit2.score", ["--tokenizer_ckpt", tokenizer, "--frames", tmp_path / "bad.npz"]),
                         "missing": ("magvit2.score", ["--tokenizer_ckpt", tokenizer, "--frames",
                                                       tmp_path / "none.npz"])})
    assert procs["bad"].returncode == 1 and "no 'frames' array" in procs["bad"].stderr
    assert procs["missing"].returncode == 1 and "no such file" in procs["missing"].stderr
    assert "Traceback" not in procs["bad"].stderr + procs["missing"].stderr
