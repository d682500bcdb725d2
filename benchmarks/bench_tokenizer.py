"""Tokenizer throughput: tokens/s for encode (images -> token ids) and decode (token ids -> images).

Two shapes: 64x64 with a small 3-level tokenizer (16x16 tokens) and 256x256 with the 1X tokenizer config
(5 levels, 16x16 tokens). Random weights (speed does not depend on them). CPU always, CUDA (bf16 autocast) when present.

    python benchmarks/bench_tokenizer.py [--iters 3]
"""
import argparse
import sys
import time

import numpy as np
import torch

from common.cli import positive_int, run_main
from magvit2 import VQConfig, VQModel

SHAPES = {
    "64x64 small (3 levels)": (VQConfig(base_channels=64, ch_mult=[1, 2, 2], resolution=64), {"cpu": 8, "cuda": 128}),
    "256x256 1X config": (VQConfig(), {"cpu": 2, "cuda": 32}),
}


def timed(fn, iters: int, device: str) -> float:
    fn()  # warm-up
    if device == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(iters):
        fn()
    if device == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / iters


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iters", type=positive_int, default=3,
                        help="timed repetitions per measurement (after 1 warm-up)")
    parser.add_argument("--devices", nargs="+", choices=("cpu", "cuda"),
                        default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []),
                        help="devices to measure (default: cpu, and cuda when present)")
    args = parser.parse_args(argv)
    if "cuda" in args.devices and not torch.cuda.is_available():
        parser.error("--devices cuda: CUDA is not available on this machine")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    print(f"{'device':<6} {'shape':<24} {'batch':>5} {'encode tok/s':>13} {'decode tok/s':>13} "
          f"{'enc frames/s':>13} {'dec frames/s':>13}")
    rng = np.random.default_rng(0)
    for device in args.devices:
        for name, (config, batch_sizes) in SHAPES.items():
            model = VQModel(config).to(device).eval()
            batch = batch_sizes[device]
            side = config.resolution
            images = torch.from_numpy(rng.integers(0, 256, (batch, side, side, 3), dtype=np.uint8)).to(device)
            tokens = model.images_to_tokens(images, batch_size=batch)
            enc = timed(lambda: model.images_to_tokens(images, batch_size=batch), args.iters, device)
            dec = timed(lambda: model.tokens_to_images(tokens, batch_size=batch), args.iters, device)
            n_tokens = tokens.numel()
            print(f"{device:<6} {name:<24} {batch:>5} {n_tokens / enc:>13.0f} {n_tokens / dec:>13.0f} "
                  f"{batch / enc:>13.2f} {batch / dec:>13.2f}")
            del model


if __name__ == "__main__":
    sys.exit(run_main("bench_tokenizer.py", main))
