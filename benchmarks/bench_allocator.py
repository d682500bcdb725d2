"""glibc's allocator defaults against the scripts' retained memory (common/allocator.py), on a training step or on
tokenizing frames.

    python benchmarks/bench_allocator.py --genie_config recipes/sample_world.json --optimizer muon
    python benchmarks/bench_allocator.py --workload tokenize --frames data/sample/raw/val.npz

The allocator's settings are process-wide, so each measurement is a process of its own, with GENIE_DEFAULT_MALLOC=1
(glibc's defaults) or without it (retained memory); the two alternate (default, retain, retain, default, ...) so that
a machine's drift over the run falls on both alike. `train`: `benchmarks/bench_train.py` with every other argument
passed through, its seconds and minor page faults per step. `tokenize`: `python -m magvit2.tokenize_frames` on
--frames with the shipped sample-world tokenizer (other arguments passed through, e.g. --batch_size), its wall time
and minor page faults per run. Prints each run, then the mean speed-up.
"""
import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common.allocator import OPT_OUT_ENV
from common.cli import positive_int, run_main
from sample_world.build import SHIPPED_TOKENIZER, resolve_tokenizer

BENCH_TRAIN = Path(__file__).with_name("bench_train.py")
TRAIN_LINE = re.compile(r"([0-9.]+) s/step .*?([0-9,]+) minor page faults per step")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                epilog="Other arguments go to the measured script (bench_train.py: e.g. --genie_config, "
                                       "--steps; tokenize_frames: e.g. --batch_size).")
    p.add_argument("--workload", choices=["train", "tokenize"], default="train",
                   help="train: bench_train.py's training steps; tokenize: magvit2.tokenize_frames on --frames")
    p.add_argument("--frames", type=Path, default=None,
                   help="tokenize: an .npz of frames (e.g. data/sample/raw/val.npz, which ./build.sh renders)")
    p.add_argument("--tokenizer_ckpt", default=SHIPPED_TOKENIZER, help="tokenize: the tokenizer's directory")
    p.add_argument("--rounds", type=positive_int, default=2,
                   help="Pairs of runs (each pair one of each allocator, the order alternating)")
    args, passthrough = p.parse_known_args(argv)
    if args.workload == "tokenize" and (args.frames is None or not args.frames.is_file()):
        p.error(f"--workload tokenize needs --frames, an existing .npz file (got {args.frames})")
    return args, passthrough


def child_faults() -> int:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt


def run(args, allocator: str, passthrough, out_dir: Path) -> float:
    """One process of the workload -> its seconds (per step for train, per run for tokenize); prints one line."""
    env = {k: v for k, v in os.environ.items() if k != OPT_OUT_ENV}
    if allocator == "default":
        env[OPT_OUT_ENV] = "1"
    if args.workload == "train":
        command = [sys.executable, str(BENCH_TRAIN), *passthrough]
    else:
        command = [sys.executable, "-m", "magvit2.tokenize_frames", str(args.frames), "--tokenizer_ckpt",
                   str(resolve_tokenizer(args.tokenizer_ckpt)), "--output_dir", str(out_dir), "--overwrite",
                   *passthrough]
    faults0, t0 = child_faults(), time.perf_counter()
    out = subprocess.run(command, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        said = (out.stderr.strip().splitlines() or ["no message"])[-1]  # the measured script's own error line
        raise SystemExit(f"bench_allocator.py: error: {' '.join(command[1:3])} ({allocator} allocator) failed with "
                         f"exit status {out.returncode}: {said}")
    if args.workload == "tokenize":  # the whole process, timed from here
        seconds, faults = time.perf_counter() - t0, child_faults() - faults0
        print(f"{allocator:>8}: {seconds:.2f} s, {faults:,.0f} minor page faults", flush=True)
        return seconds
    match = TRAIN_LINE.search(out.stdout)  # the timed steps, as bench_train.py measured them
    if match is None:
        raise SystemExit(f"bench_allocator.py: error: bench_train.py printed no step time with page faults "
                         f"(its output: {' '.join(out.stdout.split())[-500:]})")
    seconds, faults = float(match.group(1)), float(match.group(2).replace(",", ""))
    print(f"{allocator:>8}: {seconds:.3f} s/step, {faults:,.0f} minor page faults per step", flush=True)
    return seconds


def main(argv=None) -> None:
    args, passthrough = parse_args(argv)
    times = {"default": [], "retain": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.rounds):
            for allocator in (("default", "retain") if i % 2 == 0 else ("retain", "default")):
                times[allocator].append(run(args, allocator, passthrough, Path(tmp) / "tokens"))
    default, retain = statistics.mean(times["default"]), statistics.mean(times["retain"])
    unit = "s/step" if args.workload == "train" else "s"
    print(f"{args.workload}: retained memory vs glibc's defaults: {default / retain:.3f}x "
          f"(means of {args.rounds} runs each: {default:.3f} against {retain:.3f} {unit})")


if __name__ == "__main__":
    sys.exit(run_main("bench_allocator.py", main))
