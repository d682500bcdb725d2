"""Challenge evaluation and generation speed: full recomputation (the published protocol) vs the temporal KV cache.

    python benchmarks/bench_eval.py --device cpu         # 8 layers, d_model 256, 16x16 tokens, T 16, CPU fp32
    python benchmarks/bench_eval.py --device cuda --dtype bf16 --num_layers 32   # GENIE_35M shape on a GPU

Both evaluators run the same weights on the same synthetic validation windows (written with the data API and read
back with the challenge's window 16 / stride 15 / non-overlapping filter). The full-recomputation evaluator is
genie.reference.teacher_forced_uncached, the published protocol: for every target frame t and every MaskGIT step it
recomputes the whole window with ground truth before t and masks from t on. Ours is genie.inference.teacher_forced
(context once, all targets in one cached pass per step). Prints seconds per generated frame for both, the ratio, and whether the
metrics agree (CE to tolerance; sampled tokens identical at temperature 0). Then autoregressive generation
(8 prompt frames -> 16) with and without the cache.
"""
import argparse
import contextlib
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import genie
from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, non_negative_int, positive_int,
                        resolve_device, run_main)
from data import RawTokenDataset, write_token_dataset
from genie import GenieConfig, STMaskGIT
from genie.metrics import factored_cross_entropy
from genie.inference import generate_frames, teacher_forced
from genie.reference import generate_uncached, teacher_forced_uncached

CONFIG_PATH = Path(genie.__file__).parent / "configs" / "magvit_n8_h8_d256.json"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint_dir", default=None,
                   help="Benchmark these weights (default: a randomly initialized model of --num_layers).")
    p.add_argument("--num_layers", type=positive_int, default=8, help="Layers of the random model (8: benchmark shape, "
                                                             "32: GENIE_35M).")
    p.add_argument("--num_windows", type=positive_int, default=2, help="Validation windows to evaluate.")
    p.add_argument("--batch_size", type=positive_int, default=1, help="Windows per forward pass.")
    p.add_argument("--maskgit_steps", type=positive_int, default=2, help="MaskGIT steps per frame.")
    add_device_arg(p)
    p.add_argument("--dtype", choices=("fp32", "bf16"), default="fp32", help="bf16 runs under autocast (CUDA).")
    p.add_argument("--seed", type=non_negative_int, default=0, help="Seed of the weights, data and sampler.")
    p.add_argument("--skip_generation", action="store_true", help="Only benchmark teacher-forced evaluation.")
    add_num_threads_arg(p)
    return p.parse_args(argv)


def build_model(args) -> STMaskGIT:
    if args.checkpoint_dir:
        return STMaskGIT.from_pretrained(args.checkpoint_dir)
    config = dataclasses.replace(GenieConfig.from_pretrained(CONFIG_PATH), num_layers=args.num_layers)
    model = STMaskGIT(config)
    model.init_weights()
    with torch.no_grad():  # position-dependent, non-uniform predictions make the metric comparison meaningful
        model.pos_embed_TSC.normal_(0, 0.5)
        model.out_x_proj.weight.normal_(0, config.d_model ** -0.5)
    return model.eval()


def synthetic_windows(config: GenieConfig, num_windows: int, seed: int, root: Path) -> torch.Tensor:
    """Slowly changing token videos in the 1X layout, read back as challenge windows -> (N, T, H, W)."""
    rng = np.random.default_rng(seed)
    T, stride, s = config.T, 15, config.H
    frames = (T - 1) * stride + 1
    video = rng.integers(0, config.image_vocab_size, size=(num_windows * frames, s, s))
    changes = rng.random(video.shape) < 0.9  # keep 10% of each frame's tokens from the previous frame
    for i in range(1, len(video)):
        video[i] = np.where(changes[i], video[i], video[i - 1])
    write_token_dataset(root / "val", video, segment_ids=np.repeat(np.arange(num_windows), frames),
                        metadata={"vocab_size": config.image_vocab_size})
    dataset = RawTokenDataset(root / "val", window_size=T, stride=stride, filter_overlaps=True)
    return torch.stack([dataset[i]["tokens"] for i in range(num_windows)])


class Timer:
    """Accumulates wall-clock and process CPU seconds (CPU time is steadier on a busy machine with 1 thread)."""

    def __init__(self, device):
        self.device, self.wall, self.cpu = device, 0.0, 0.0

    @contextlib.contextmanager
    def __call__(self):
        sync(self.device)
        wall, cpu = time.perf_counter(), time.process_time()
        yield
        sync(self.device)
        self.wall += time.perf_counter() - wall
        self.cpu += time.process_time() - cpu


def compare_evaluators(model, windows, args, device, autocast) -> dict:
    """Both evaluators on every batch, interleaved so that both see the same machine load.

    -> {name: (Timer, CE, acc, samples)}
    """
    evaluators = {"full": teacher_forced_uncached, "ours": teacher_forced}
    state = {name: dict(timer=Timer(device), generator=torch.Generator(device=device).manual_seed(args.seed),
                        ce=0.0, correct=0, samples=[]) for name in evaluators}
    for a in range(0, len(windows), args.batch_size):
        x = windows[a:a + args.batch_size].to(device)
        for name, fn in evaluators.items():
            st = state[name]
            with st["timer"](), torch.no_grad(), autocast:
                samples, logits = fn(model, x, args.maskgit_steps, generator=st["generator"])
            st["ce"] += factored_cross_entropy(logits, x[:, 1:]).sum().item()
            st["correct"] += (samples == x[:, 1:]).sum().item()
            st["samples"].append(samples.cpu())
    num_tokens = windows[:, 1:].numel()
    return {name: (st["timer"], st["ce"] / num_tokens, st["correct"] / num_tokens, torch.cat(st["samples"]))
            for name, st in state.items()}


def timed_generation(model, windows, args, device, autocast, use_cache: bool, num_prompt: int = 8) -> Timer:
    generator = torch.Generator(device=device).manual_seed(args.seed)
    timer = Timer(device)
    for a in range(0, len(windows), args.batch_size):
        prompt = windows[a:a + args.batch_size, :num_prompt].to(device)
        with timer(), autocast:
            (generate_frames if use_cache else generate_uncached)(model, prompt, windows.shape[1] - num_prompt,
                                                                  args.maskgit_steps, generator=generator)
    return timer


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv=None):
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    device = resolve_device(args.device)
    torch.manual_seed(args.seed)
    model = build_model(args).to(device)
    config = model.config
    autocast = (torch.autocast(device.type, dtype=torch.bfloat16) if args.dtype == "bf16"
                else contextlib.nullcontext())
    with tempfile.TemporaryDirectory() as tmp:
        windows = synthetic_windows(config, args.num_windows, args.seed, Path(tmp))
    print(f"device {device} ({torch.get_num_threads()} threads), {args.dtype}, torch {torch.__version__}; model "
          f"{config.num_layers} layers, d_model {config.d_model}, T {config.T}, {config.H}x{config.W} tokens; "
          f"{args.num_windows} windows, batch {args.batch_size}, maskgit_steps {args.maskgit_steps}")

    with torch.no_grad(), autocast:  # warm-up (allocator, kernels)
        teacher_forced(model, windows[:1].to(device), 1)

    results = compare_evaluators(model, windows, args, device, autocast)
    (full_timer, full_ce, full_acc, full_samples), (ours_timer, ours_ce, ours_acc, ours_samples) = \
        results["full"], results["ours"]
    frames = len(windows) * (windows.shape[1] - 1)
    same = (full_samples == ours_samples).float().mean().item()
    ce_tol = 1e-4 if args.dtype == "fp32" else 2e-2
    agree = abs(full_ce - ours_ce) <= ce_tol * full_ce and (args.dtype != "fp32" or same > 0.999)
    print(f"teacher-forced evaluation, s per generated frame: full recomputation {full_timer.wall / frames:.4f}, "
          f"ours (KV cache) {ours_timer.wall / frames:.4f}, speed-up {full_timer.wall / ours_timer.wall:.1f}x "
          f"(process CPU time: {full_timer.cpu / frames:.4f} vs {ours_timer.cpu / frames:.4f}, "
          f"{full_timer.cpu / ours_timer.cpu:.1f}x)")
    print(f"  metrics: CE {full_ce:.5f} vs {ours_ce:.5f}; acc {full_acc:.5f} vs {ours_acc:.5f}; "
          f"identical sampled tokens {100 * same:.2f}% -> {'agree' if agree else 'DISAGREE'}")

    if not args.skip_generation:
        new_frames = len(windows) * (windows.shape[1] - 8)
        no_cache = timed_generation(model, windows, args, device, autocast, use_cache=False)
        cache = timed_generation(model, windows, args, device, autocast, use_cache=True)
        print(f"autoregressive generation (8 prompt frames -> 16), s per frame: without cache "
              f"{no_cache.wall / new_frames:.4f}, with cache {cache.wall / new_frames:.4f}, speed-up "
              f"{no_cache.wall / cache.wall:.1f}x (process CPU time: {no_cache.cpu / new_frames:.4f} vs "
              f"{cache.cpu / new_frames:.4f}, {no_cache.cpu / cache.cpu:.1f}x)")
    if not agree:
        raise SystemExit("bench_eval.py: error: the two evaluators disagree")


if __name__ == "__main__":
    sys.exit(run_main("bench_eval.py", main))
