"""Training throughput (tokens/s) of STMaskGIT: the issue's reference shape, one full optimizer step per iteration.

    python benchmarks/bench_train.py --device cpu          # 8 layers, d_model 256, T 16, 16x16, batch 2, fp32, CPU
    python benchmarks/bench_train.py --mixed_precision compare  # fp32 vs CPU bf16 autocast (avx512_bf16 / AMX)
    python benchmarks/bench_train.py --readout compare          # logits of every token vs of the masked ones only
    python benchmarks/bench_train.py --optimizer compare        # AdamW vs Muon + AdamW (train.py --optimizer)
    python benchmarks/bench_train.py --genie_config genie/configs/sample_world.json --profile   # the CPU default
    python benchmarks/bench_train.py --device cuda --mixed_precision bf16 --compile --batch_size 16
    python benchmarks/bench_allocator.py --genie_config recipes/sample_world.json --optimizer muon   # the main model
                                                           # glibc's allocator defaults vs retained memory
                                                           # (GENIE_DEFAULT_MALLOC=1: this script with glibc's)

A step is what train.py does per optimizer step: MaskGIT collation of a batch of windows, forward, backward,
gradient clipping and the optimizer train.py builds (AdamW unless --optimizer muon); with --genie_config, under that
config's training recipe (--recipe) and, for a model with action inputs, with random action streams. Tokens per
step = batch * T * S. The published implementation trains this shape at ~1,840 tokens/s on the project's 2-core CPU
(fp32, batch 2); the ratio to that figure is printed (it is only meaningful for that shape on that machine).
"""
import argparse
import sys
import time
from typing import Optional

try:
    import resource
except ImportError:  # not a Unix
    resource = None

import torch

from common.cli import (NO_NATIVE_BF16, add_device_arg, add_num_threads_arg, apply_cpu_settings, cpu_has_native_bf16,
                        non_negative_int, positive_int, resolve_device, run_main)
from common.muon import build_optimizer
from training.action_streams import LATENT_ACTION_NAME
from training.masking import get_maskgit_collator
from training.recipe import load_model_config
from genie.transformer import set_cpu_bf16_math
from genie.config import GenieConfig, TrainingRecipe
from genie.model import STMaskGIT
from genie.reference import full_logits_loss

PUBLISHED_TOKENS_PER_S = 1840.0


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="Measure STMaskGIT training tokens/s.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--genie_config", default=None,
                   help="Benchmark the model of this config JSON, or of a run recipe's model (e.g. "
                        "genie/configs/sample_world.json, with its copy head, or recipes/sample_world.json) instead "
                        "of the shape flags below (--batch_size still applies).")
    p.add_argument("--recipe", default="config", choices=("config", "published"),
                   help="With --genie_config: train with the config's training recipe, as train.py does (e.g. "
                        "its self_reveal_ratio adds a pass without gradients for that share of the examples), or "
                        "with the published one (masking and loss only). Without --genie_config: the published one.")
    p.add_argument("--num_layers", type=positive_int, default=8, help="Transformer blocks.")
    p.add_argument("--d_model", type=positive_int, default=256, help="Model width.")
    p.add_argument("--num_heads", type=positive_int, default=8, help="Attention heads.")
    p.add_argument("--T", type=positive_int, default=16, help="Frames per window.")
    p.add_argument("--s", type=positive_int, default=16, help="Token grid side (S = s * s).")
    p.add_argument("--image_vocab_size", type=positive_int, default=262144, help="Image token vocabulary.")
    p.add_argument("--batch_size", type=positive_int, default=2, help="Windows per step.")
    p.add_argument("--warmup_steps", type=non_negative_int, default=2, help="Untimed steps first.")
    p.add_argument("--steps", type=positive_int, default=5, help="Timed steps.")
    add_device_arg(p)
    p.add_argument("--mixed_precision", default="no", choices=("no", "bf16", "compare"),
                   help="bf16 autocast (CUDA, or CPUs with native bf16 such as avx512_bf16); compare: fp32, then "
                        "bf16 with torch's fused attention kernel, then bf16 with the written-out CPU path for the "
                        "temporal attention, each on a fresh model, with the ratios.")
    p.add_argument("--readout", default="masked", choices=("masked", "full", "compare"),
                   help="masked: the loss reads out only the masked tokens it counts (what train.py does); full: "
                        "logits of every token, as published; compare: full, then masked, with the ratio.")
    p.add_argument("--optimizer", default="adamw", choices=("adamw", "muon", "compare"),
                   help="The optimizer train.py builds with --optimizer adamw / muon; compare: both, with the ratio.")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the whole model, as train.py does on CUDA (CUDA only).")
    add_num_threads_arg(p)
    p.add_argument("--profile", action="store_true", help="Print the top operators of one profiled step.")
    args = p.parse_args(argv)
    if [args.readout, args.mixed_precision, args.optimizer].count("compare") > 1:
        p.error("compare one thing at a time (--readout, --mixed_precision or --optimizer)")
    if args.compile and resolve_device(args.device).type != "cuda":
        p.error("--compile is for CUDA (--device cuda): on the CPU it measured no gain and was removed")
    return args


def make_step(model, optimizer, collate, windows, device, mixed_precision, full_readout: bool = False,
              recipe: Optional[TrainingRecipe] = None):
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=mixed_precision == "bf16")

    def step():
        batch = collate(windows).to(device)
        with autocast:
            loss = (full_logits_loss(model, batch) if full_readout else model(batch, recipe)).loss
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if device.type == "cuda":
            torch.cuda.synchronize()
        return loss.item()
    return step


def build(args, device, optimizer_name: str = "adamw"):
    recipe = TrainingRecipe()
    if args.genie_config:
        config, config_recipe = load_model_config(args.genie_config)
        if args.recipe == "config":
            recipe = config_recipe
    else:
        config = GenieConfig(num_layers=args.num_layers, num_heads=args.num_heads, d_model=args.d_model, T=args.T,
                             S=args.s ** 2, image_vocab_size=args.image_vocab_size)
    torch.manual_seed(0)
    model = STMaskGIT(config)
    model.init_weights()
    model.to(device).train()
    optimizer = build_optimizer(model.parameters(), model.decoder.parameters(), optimizer_name, lr=1e-4,
                                weight_decay=0.0, fused=device.type in ("cuda", "cpu"))  # as train.py builds it
    generator = torch.Generator().manual_seed(0)
    windows = [{"tokens": torch.randint(0, config.image_vocab_size, (config.T, config.H, config.W),
                                        generator=generator),
                "actions": random_action_streams(config, generator)} for _ in range(args.batch_size)]
    return config, recipe, model, optimizer, windows


def random_action_streams(config: GenieConfig, generator: torch.Generator) -> dict:
    """Random per-frame action streams (name -> (T, k)) for an action-conditioned config: only their concatenated
    width matters to the model, so the first stream gets all action_dim columns and the others none."""
    streams = {}
    for i, name in enumerate(config.action_names or []):
        streams[name] = torch.randn(config.T, config.action_dim if i == 0 else 0, generator=generator)
    if config.num_latent_actions:
        streams[LATENT_ACTION_NAME] = torch.randint(0, config.num_latent_actions, (config.T, 1),
                                                    generator=generator).float()
    return streams


def measure(args, device, mixed_precision: str, math_path: bool, full_readout: bool = False,
            optimizer_name: str = "adamw") -> float:
    """Seconds per optimizer step (wall) of a freshly built model; prints one line."""
    config, recipe, model, optimizer, windows = build(args, device, optimizer_name)
    set_cpu_bf16_math(model, math_path)
    compiled = torch.compile(model) if args.compile else model  # as train.py compiles on CUDA
    step = make_step(compiled, optimizer, get_maskgit_collator(config, recipe, seed=0), windows, device,
                     mixed_precision, full_readout, recipe)
    for _ in range(args.warmup_steps):
        step()
    faults0 = minor_page_faults()
    t0, cpu0 = time.perf_counter(), time.process_time()
    for _ in range(args.steps):
        step()
    seconds = (time.perf_counter() - t0) / args.steps
    cpu_seconds = (time.process_time() - cpu0) / args.steps  # all threads: compare with wall time on busy machines
    faults = None if faults0 is None else (minor_page_faults() - faults0) / args.steps
    tokens_per_s = args.batch_size * config.T * config.S / seconds
    label = "fp32" if mixed_precision == "no" else "bf16" if device.type != "cpu" else \
        f"bf16 ({'written-out temporal' if math_path else 'fused'} attention)"
    label += ", all logits" if full_readout else ""
    label += ", Muon + AdamW" if optimizer_name == "muon" else ""
    print(f"{label:>42}: {seconds:.3f} s/step (process CPU time {cpu_seconds:.3f} s/step), "
          f"{tokens_per_s:,.0f} tokens/s, {tokens_per_s / PUBLISHED_TOKENS_PER_S:.2f}x the published "
          f"{PUBLISHED_TOKENS_PER_S:,.0f} tokens/s"
          + ("" if faults is None else f", {faults:,.0f} minor page faults per step"), flush=True)
    if args.profile:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            step()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))
    return seconds


def minor_page_faults() -> Optional[int]:
    """This process's minor page faults so far (pages the kernel mapped in without I/O), None where unknown."""
    return None if resource is None else resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def main(argv=None) -> None:
    args = parse_args(argv)
    device = resolve_device(args.device)
    apply_cpu_settings(args.num_threads)
    config, recipe, model = build(args, device)[:3]
    params = sum(p.numel() for p in model.parameters())
    print(f"STMaskGIT {config.num_layers} layers, d_model {config.d_model}, T {config.T}, {config.H}x{config.W}, "
          f"{params / 1e6:.1f} M params, batch {args.batch_size}, {device.type}, threads {torch.get_num_threads()}")
    if device.type == "cpu" and args.mixed_precision != "no":
        kinds = {True: "native", False: f"emulated ({NO_NATIVE_BF16})",
                 None: "unknown (no CPU flags to read)"}
        print(f"this CPU's bf16: {kinds[cpu_has_native_bf16()]}")
    if args.readout == "compare":
        full = measure(args, device, args.mixed_precision, math_path=True, full_readout=True)
        masked = measure(args, device, args.mixed_precision, math_path=True)
        print(f"masked-token readout vs all logits: {full / masked:.2f}x")
        return
    if args.optimizer == "compare":
        adamw = measure(args, device, args.mixed_precision, math_path=True)
        muon = measure(args, device, args.mixed_precision, math_path=True, optimizer_name="muon")
        print(f"Muon + AdamW vs AdamW: {adamw / muon:.2f}x")
        return
    if args.mixed_precision != "compare":
        measure(args, device, args.mixed_precision, math_path=True, full_readout=args.readout == "full",
                optimizer_name=args.optimizer)
        return
    fp32 = measure(args, device, "no", math_path=True)
    runs = {"fused": measure(args, device, "bf16", math_path=False),
            "written-out temporal": measure(args, device, "bf16", math_path=True)}
    for name, seconds in runs.items():
        print(f"bf16 ({name} attention) vs fp32: {fp32 / seconds:.2f}x")


if __name__ == "__main__":
    sys.exit(run_main("bench_train.py", main))
