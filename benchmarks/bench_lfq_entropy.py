"""Peak memory (and time) of the LFQ entropy loss, forward + backward: factorized (ours) vs the naive (N, 2^C) form.

Default: a 2^18 codebook at batch 8 of 16x16 latents (N = 2048), the 1X tokenizer's training shape. On CPU each
method runs in a fresh process and its peak is the growth of the process's max resident set size; on CUDA it is
torch.cuda.max_memory_allocated. The naive form needs several (N, 2^18) fp32 tensors (2 GiB each).

    python benchmarks/bench_lfq_entropy.py [--device cuda] [--skip_naive]
"""
import argparse
import multiprocessing as mp
import resource
import sys
import time

import torch

from common.cli import add_device_arg, positive_int, resolve_device, run_main
from magvit2.lfq import entropy_terms, naive_entropy_terms

METHODS = {"factorized": entropy_terms, "naive": naive_entropy_terms}


def measure(method: str, num_latents: int, num_channels: int, device: str) -> dict:
    """Run one forward + backward of the entropy loss; return peak extra memory (bytes), seconds and the loss."""
    torch.manual_seed(0)
    warm_up = torch.randn(16, 4, device=device, requires_grad=True)  # load kernels before the baseline
    sum(METHODS[method](warm_up)).backward()
    z = (torch.randn(num_latents, num_channels, device=device) * 0.01).requires_grad_()
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    start = time.perf_counter()
    per_sample, codebook = METHODS[method](z)
    loss = per_sample - codebook
    loss.backward()
    if device == "cuda":
        torch.cuda.synchronize()
        peak = torch.cuda.max_memory_allocated() - base
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
    return {"peak_bytes": peak, "seconds": time.perf_counter() - start, "loss": loss.item()}


def _child(queue, *args):
    queue.put(measure(*args))


def measure_in_fresh_process(*args) -> dict:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(queue, *args))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch_size", type=positive_int, default=8, help="images per batch")
    parser.add_argument("--latent_side", type=positive_int, default=16,
                        help="latent grid side (16 for 256x256 images)")
    parser.add_argument("--num_channels", type=positive_int, default=18,
                        help="LFQ bits; the codebook has 2^num_channels codes")
    add_device_arg(parser)
    parser.add_argument("--skip_naive", action="store_true", help="do not run the naive form (it needs ~10 GiB)")
    args = parser.parse_args(argv)
    device = str(resolve_device(args.device))
    n = args.batch_size * args.latent_side ** 2
    print(f"LFQ entropy loss, forward + backward: N = {n} latents, codebook 2^{args.num_channels}, "
          f"device {device}")
    results = {}
    for method in ["factorized"] + ([] if args.skip_naive else ["naive"]):
        run = measure if device == "cuda" else measure_in_fresh_process
        results[method] = run(method, n, args.num_channels, device)
        r = results[method]
        print(f"  {method:>10}: peak {r['peak_bytes'] / 2 ** 20:10.1f} MiB   {r['seconds']:7.3f} s   "
              f"loss {r['loss']:.6f}")
    if "naive" in results:
        ratio = results["naive"]["peak_bytes"] / max(results["factorized"]["peak_bytes"], 1)
        print(f"  naive / factorized peak memory: {ratio:.0f}x; "
              f"|loss difference| = {abs(results['naive']['loss'] - results['factorized']['loss']):.2e}")


if __name__ == "__main__":
    sys.exit(run_main("bench_lfq_entropy.py", main))
