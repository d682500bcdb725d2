"""The copy ceiling (evaluation/copy_ceiling.py, python diagnose.py copy_ceiling): hand-made frames whose best
copies are known."""
import numpy as np
import pytest
import torch

from data import write_token_dataset
from common.cli import run_main
from evaluation.copy_ceiling import best_copies, ceiling_rollout, code_distances, neighbours
from diagnose import main
from tests.test_evaluate import ROLLOUT_KEYS, error_line, last_json_line, tiny  # noqa: F401 (tiny: a fixture)

SAMPLER_KEYS = {"maskgit_steps", "temperature", "unmask_mode", "copy_bias", "greedy_tokens", "stall_ratio"}


def ceiling_args(data, *extra):
    return ["copy_ceiling", "--val_data_dir", str(data), "--window_size", "8", "--stride", "3", "--batch_size", "3",
            "--device", "cpu", *extra]


def shifted(frame_BHW: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """frame_BHW moved so that position (y, x) shows what (y + dy, x + dx) showed, edges extended."""
    H, W = frame_BHW.shape[-2:]
    rows = (torch.arange(H) + dy).clamp(0, H - 1)
    cols = (torch.arange(W) + dx).clamp(0, W - 1)
    return frame_BHW[:, rows][:, :, cols]


def test_code_distances_count_differing_bits():
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 2 ** 18, 200), rng.integers(0, 2 ** 18, 200)
    expected = [bin(int(x) ^ int(y)).count("1") for x, y in zip(a, b)]
    assert code_distances(torch.tensor(a), torch.tensor(b), 18).tolist() == expected
    assert code_distances(torch.tensor([2 ** 18 + 1]), torch.tensor([1]), 18).tolist() == [0]  # num_bits only


def test_neighbours_are_row_major_offsets_with_edges_extended():
    frame = torch.arange(12).view(1, 3, 4)
    n = neighbours(frame, 1)
    assert n.shape == (1, 3, 4, 9)
    offsets = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    for k, (dy, dx) in enumerate(offsets):
        assert torch.equal(n[..., k], shifted(frame, dy, dx))
    assert n[0, 0, 0].tolist() == [0, 0, 1, 0, 0, 1, 4, 4, 5]


@pytest.mark.parametrize("block", [1, 2, 4])
def test_a_whole_token_shift_is_copied_exactly(block):
    prev = torch.randint(0, 2 ** 18, (2, 4, 4))
    true = shifted(prev, 1, -2)
    copies, exact = best_copies(prev, true, radius=2, block=block, num_bits=18)
    assert torch.equal(copies, true) and exact.all()
    assert not best_copies(prev, true, radius=1, block=block, num_bits=18)[1].all()  # out of reach


def test_each_position_copies_its_nearest_code():
    prev, true = torch.randint(0, 2 ** 6, (2, 4, 5)), torch.randint(0, 2 ** 6, (2, 4, 5))
    n = neighbours(prev, 1)
    offsets = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    expected = torch.empty_like(true)
    for b, y, x in np.ndindex(*true.shape):  # least distance, then least displacement, then row-major order
        keys = [(bin(int(n[b, y, x, k]) ^ int(true[b, y, x])).count("1"), abs(dy) + abs(dx), k)
                for k, (dy, dx) in enumerate(offsets)]
        expected[b, y, x] = n[b, y, x, min(keys)[2]]
    copies, exact = best_copies(prev, true, radius=1, block=1, num_bits=6)
    assert torch.equal(copies, expected) and torch.equal(exact, expected == true)


def test_ties_go_to_the_smaller_displacement():
    prev = torch.full((1, 3, 3), 0b11)
    prev[0, 1, 1], prev[0, 1, 2] = 0b01, 0b10  # centre and its right neighbour: one bit from the truth each
    copies, exact = best_copies(prev, torch.zeros(1, 3, 3, dtype=torch.long), radius=1, block=1, num_bits=2)
    assert copies[0, 1, 1] == 0b01 and not exact.any()


def test_blocks_share_one_displacement():
    prev = torch.randint(0, 2 ** 18, (1, 4, 4))
    true = torch.cat([shifted(prev, 0, 1)[..., :2], shifted(prev, 0, -1)[..., 2:]], dim=-1)  # halves move apart
    assert best_copies(prev, true, radius=1, block=2, num_bits=18)[1].all()
    whole = best_copies(prev, true, radius=1, block=4, num_bits=18)[1]
    assert 0 < whole.float().mean() < 1  # one shift fits one half, not both


def test_the_ceiling_rollout_compounds_on_its_own_frames():
    x = torch.randint(0, 2 ** 18, (2, 6, 4, 4))
    for t in range(1, 6):
        x[:, t] = shifted(x[:, t - 1], 0, 1)  # the camera pans one token per frame: edge tokens repeat
    out, exact = ceiling_rollout(x, 3, radius=1, block=1, num_bits=18)
    assert torch.equal(out, x) and exact.tolist() == [3 * 16, 3 * 16]
    held, _ = ceiling_rollout(x, 3, radius=0, block=1, num_bits=18)  # radius 0: holding the last prompt frame
    assert all(torch.equal(held[:, t], x[:, 2]) for t in range(3, 6))


def test_copy_ceiling_protocol_json_line(tiny, tmp_path, capsys):
    args = ceiling_args(tiny.data, "--num_prompt_frames", "3", "--max_examples", "4", "--tokenizer_ckpt",
                        str(tiny.tokenizer), "--skip_lpips")
    assert main(args + ["--ceiling_radius", "0"]) == 0
    held = last_json_line(capsys.readouterr().out)
    assert set(held) == (ROLLOUT_KEYS - SAMPLER_KEYS) | {"radius", "block", "exact_share"}
    assert (held["protocol"], held["radius"], held["block"], held["gen_time"]) == ("copy_ceiling", 0, 1, None)
    assert held["rollout_psnr"] == held["hold_psnr"]  # radius 0 copies the last prompt frame over and over
    assert held["rollout_unchanged"][1:] == [1.0] * 4


def test_the_ceiling_follows_a_panning_camera(tiny, tmp_path, capsys):
    """Frame i shows columns i..i+3 of a wide random picture: each frame is the one before moved by a column, with
    a new column entering at the right edge, which no copy can know (the nearest code stands in for it)."""
    pattern = np.random.default_rng(1).integers(0, 64 ** 2, size=(4, 124))
    video = np.stack([pattern[:, i:i + 4] for i in range(120)])
    write_token_dataset(tmp_path / "pan", video, segment_ids=np.zeros(120, dtype=np.int64),
                        metadata={"vocab_size": 64 ** 2})
    args = ceiling_args(tmp_path / "pan", "--stride", "1", "--num_prompt_frames", "3", "--max_examples", "6",
                        "--tokenizer_ckpt", str(tiny.tokenizer), "--skip_lpips")
    results = {}
    for radius, block in ((0, 1), (1, 1), (1, 4)):
        assert main(args + ["--ceiling_radius", str(radius), "--ceiling_block", str(block)]) == 0
        results[radius, block] = last_json_line(capsys.readouterr().out)
    assert results[0, 1]["exact_share"] < 0.01
    # copies of its own frames: each step is exact but for the entering column, whose guess the next steps carry
    # along, so of the 4 columns 3, 2, 1, 0, 0 are right over the 5 horizons
    for result in (results[1, 1], results[1, 4]):
        assert result["exact_share"] == pytest.approx(6 / 20, abs=0.02)
        assert result["rollout_psnr"][0] > result["hold_psnr"][0]


@pytest.mark.parametrize("extra, code, message", [
    (["--ceiling_radius", "-1"], 2, "--ceiling_radius must be >= 0"),
    (["--ceiling_block", "0"], 2, "--ceiling_block >= 1, got 2 and 0"),
    (["--stall_ratio", "0.5"], 2, "unrecognized arguments: --stall_ratio"),  # a decoding rule: no model here
    (["--checkpoint_dir", "ckpt"], 2, "unrecognized arguments: --checkpoint_dir"),
    (["--num_prompt_frames", "8"], 2, "--num_prompt_frames must be in 1..7"),
    (["--num_prompt_frames", "3", "--ceiling_block", "3"], 1, "--ceiling_block 3 does not divide the 4 x 4"),
])
def test_bad_copy_ceiling_flags(tiny, capsys, extra, code, message):
    if code == 2:
        with pytest.raises(SystemExit) as exit_info:
            main(ceiling_args(tiny.data, *extra))
        assert exit_info.value.code == 2
    else:
        assert run_main("diagnose.py", main,
                        ceiling_args(tiny.data, *extra, "--tokenizer_ckpt", "unused", "--skip_lpips")) == code
    line = error_line(capsys.readouterr().err)
    assert ": error: " in line and message in line
