"""Tokenizer training throughput of `python -m magvit2.train` on this machine, for a few speed settings.

    python benchmarks/bench_tokenizer_train.py                      # the sample-world tokenizer: 64x64, batch 16
    python benchmarks/bench_tokenizer_train.py --base_channels 32 --num_res_blocks 1 --steps 10

Runs the real training CLI (model, LPIPS when its weights are installed, EMA, AdamW) on synthetic frames, once
for 1 step and once for 1 + --steps steps per setting, and prints from the difference steps/s, frames/s and CPU
seconds per step (which, unlike wall time, is not inflated by other processes competing for the cores).
Each run is its own process: accelerate fixes the precision once per process.
"""
import argparse
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from common.cli import positive_int, run_main
from magvit2.lpips import LPIPSWeightsNotFound, resolve_lpips_weights

SETTINGS = {
    "fp32": [],
    "fp32+channels_last": ["--channels_last"],
    "bf16+channels_last": ["--mixed_precision", "bf16", "--channels_last"],
}


def synthetic_frames(n: int, size: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:size, 0:size] / size
    phases = rng.uniform(0, 2 * np.pi, (n, 1, 1, 3))
    frames = np.sin(2 * np.pi * (xx[None, ..., None] + 0.5 * yy[None, ..., None]) + phases)
    return ((frames + 1) * 127.5).astype(np.uint8)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=positive_int, default=64, help="Frame side.")
    p.add_argument("--batch_size", type=positive_int, default=16, help="Frames per step.")
    p.add_argument("--base_channels", type=positive_int, default=64, help="Tokenizer width of level 0.")
    p.add_argument("--ch_mult", type=positive_int, nargs="+", default=[1, 2, 2], help="Width multipliers per level.")
    p.add_argument("--num_res_blocks", type=positive_int, default=2, help="Residual blocks per level.")
    p.add_argument("--steps", type=positive_int, default=6,
                   help="Timed training steps per setting (the difference of a 1-step and a (1 + steps)-step run).")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS),
                   help="Speed settings to compare.")
    args = p.parse_args(argv)
    try:
        resolve_lpips_weights()
        lpips_flags, lpips_note = [], "with LPIPS every step"
    except LPIPSWeightsNotFound:
        lpips_flags, lpips_note = ["--no_lpips"], "without LPIPS (no weights installed)"
    print(f"tokenizer training, {args.resolution}x{args.resolution}, batch {args.batch_size}, base_channels "
          f"{args.base_channels}, ch_mult {args.ch_mult}, num_res_blocks {args.num_res_blocks}, {lpips_note}")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "frames.npz"
        np.savez(data, frames=synthetic_frames(4 * args.batch_size, args.resolution))
        for name in args.settings:
            flags = ["--train_data", str(data), "--resolution", str(args.resolution), "--batch_size",
                     str(args.batch_size), "--base_channels", str(args.base_channels), "--ch_mult",
                     *map(str, args.ch_mult), "--num_res_blocks", str(args.num_res_blocks), "--z_channels", "18",
                     "--val_fraction", "0", "--checkpointing_steps", "0", "--device", "cpu",
                     *lpips_flags, *SETTINGS[name]]
            short = train(flags, Path(tmp) / f"{name}-1", 1)
            long = train(flags, Path(tmp) / f"{name}-n", 1 + args.steps)
            seconds_per_step = (long["seconds"] - short["seconds"]) / args.steps
            cpu_per_step = (long["cpu_seconds"] - short["cpu_seconds"]) / args.steps
            print(f"{name:>20}: {1 / seconds_per_step:.3f} steps/s, {args.batch_size / seconds_per_step:.1f} "
                  f"frames/s, {cpu_per_step:.2f} CPU-s/step")


def train(flags: list, output_dir: Path, steps: int) -> dict:
    """Run the training CLI; returns its training-loop seconds and the CPU seconds of the whole process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = subprocess.run([sys.executable, "-m", "magvit2.train", *flags, "--output_dir", str(output_dir),
                             "--max_train_steps", str(steps)], capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        said = (result.stderr.strip().splitlines() or ["no message"])[-1]  # magvit2.train's own error line
        sys.exit(f"bench_tokenizer_train.py: error: magvit2.train failed with exit status {result.returncode}: {said}")
    results = json.loads((output_dir / "eval_results.json").read_text())
    return {"seconds": steps / results["train_steps_per_second"],
            "cpu_seconds": (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)}

if __name__ == "__main__":
    sys.exit(run_main("bench_tokenizer_train.py", main))
