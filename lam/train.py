"""Train the latent action model (lam/model.py) on raw frames, then report how controllable and how meaningful its
latent actions are on the validation frames.

    python -m lam.train --train_data data/sample/raw/train.npz --val_data data/sample/raw/val.npz

Writes OUTPUT_DIR/config.json + model.safetensors (the LAM), OUTPUT_DIR/metrics.json, and every
--checkpointing_steps a copy of the model in OUTPUT_DIR/checkpoint. The final report (also printed as one JSON line):
- psnr_inferred / psnr_random / delta_psnr: PSNR of the predicted next frame decoded with the latent actions
  inferred from the true next frame vs with uniformly random latent actions; the difference is a LAM-level
  delta-PSNR (Genie): higher means the latent action controls more of the next frame. psnr_copy_last: PSNR of
  just repeating the last past frame, for scale.
- perplexity, codes_used_fraction, code_histogram: codebook usage on the validation transitions.
- action_probe_acc vs action_majority_rate: how well latent actions predict the true button actions
  (see lam/probe.py), when the files have `actions_buttons`.
"""
import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, check_optimizer_args, finite_float,
                        non_negative_int, positive_int, resolve_device, run_main, setup_logging)
from common.config import load_json
from common.errors import DataMismatchError, InputError
from common.files import write_json_atomic
from common.images import psnr
from common.schedules import lr_multiplier
from lam.data import gather_transitions, infer_codes, load_frames_npz, valid_targets
from lam.model import LAM, LAMConfig, code_usage
from lam.probe import action_probe, combination_name, transition_labels

logger = logging.getLogger("train_lam")
FRAME_RANGE = (-1.0, 1.0)  # the LAM's frames and decoder outputs


def int_list(text: str) -> list:
    """argparse type of --channels: comma-separated positive integers, e.g. 16,32,64."""
    try:
        values = [int(c) for c in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected comma-separated positive integers such as 16,32,64, got {text!r}")
    return values


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train_data", default="data/sample/raw/train.npz",
                   help="training frames: .npz with frames (N,H,W,3) uint8 and segment_ids (N,) (sample world format)")
    p.add_argument("--val_data", default="data/sample/raw/val.npz", help="validation frames, same format")
    p.add_argument("--output_dir", default="data/lam", help="where the LAM, its checkpoint and metrics.json go")
    p.add_argument("--lam_config", default=None,
                   help="LAMConfig JSON file; the flags below that are given explicitly override its fields")
    p.add_argument("--stride", type=positive_int, default=None,
                   help="raw frames between the frames a latent action connects (default 15, the dynamics "
                        "model's frame stride)")
    p.add_argument("--num_past_frames", type=positive_int, default=None,
                   help="context frames before the target (default 1)")
    p.add_argument("--codebook_size", type=positive_int, default=None, help="number of latent actions (default 8)")
    p.add_argument("--latent_dim", type=positive_int, default=None,
                   help="width of the latent action vectors (default 32)")
    p.add_argument("--channels", type=int_list, default=None,
                   help="comma-separated conv widths per level (default 16,32,64)")
    p.add_argument("--max_train_steps", type=positive_int, default=1200, help="optimizer steps")
    p.add_argument("--batch_size", type=positive_int, default=32, help="transitions per step")
    p.add_argument("--learning_rate", type=finite_float, default=1e-3, help="peak AdamW learning rate")
    p.add_argument("--weight_decay", type=finite_float, default=0.0, help="AdamW weight decay")
    p.add_argument("--warmup_steps", type=non_negative_int, default=50,
                   help="linear warm-up steps; cosine decay to 10%% after")
    p.add_argument("--max_grad_norm", type=finite_float, default=1.0, help="gradient clipping norm")
    p.add_argument("--checkpointing_steps", type=non_negative_int, default=200,
                   help="save the model to OUTPUT_DIR/checkpoint every this many steps (0: never)")
    p.add_argument("--max_eval_examples", type=non_negative_int, default=2048,
                   help="validation transitions to evaluate (evenly spaced over the file; 0: all)")
    p.add_argument("--max_probe_train_examples", type=non_negative_int, default=8192,
                   help="training transitions used to fit the action probe (random subset; 0: all)")
    p.add_argument("--eval_batch_size", type=positive_int, default=128, help="transitions per evaluation batch")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation, batch sampling and random actions")
    add_device_arg(p)
    add_num_threads_arg(p)
    args = p.parse_args(argv)
    check_optimizer_args(p, args)
    return args


def build_config(args, frames_NHWC: np.ndarray) -> LAMConfig:
    base = load_json(args.lam_config, "LAM config") if args.lam_config else {}
    overrides = {"stride": args.stride, "num_past_frames": args.num_past_frames,
                 "codebook_size": args.codebook_size, "latent_dim": args.latent_dim,
                 "channels": args.channels}
    d = {**base, **{k: v for k, v in overrides.items() if v is not None}}
    d["image_size"], d["image_channels"] = frames_NHWC.shape[1], frames_NHWC.shape[3]
    if frames_NHWC.shape[1] != frames_NHWC.shape[2]:
        raise InputError(f"{args.train_data}: frames must be square, got {frames_NHWC.shape[1:3]}")
    return LAMConfig.from_dict(d, source=args.lam_config or "train_lam flags")


def evenly_spaced(targets: np.ndarray, max_examples: int) -> np.ndarray:
    if max_examples <= 0 or len(targets) <= max_examples:
        return targets
    return targets[np.linspace(0, len(targets) - 1, max_examples).round().astype(np.int64)]


@torch.no_grad()
def evaluate(model: LAM, frames_NHWC: torch.Tensor, targets: np.ndarray, batch_size: int, device,
             seed: int = 0) -> dict:
    """Reconstruction PSNR with inferred vs random latent actions, and codebook usage, over `targets`."""
    cfg = model.config
    gen = torch.Generator().manual_seed(seed)
    sums = {"psnr_inferred": 0.0, "psnr_random": 0.0, "psnr_copy_last": 0.0}
    codes = []
    for i in tqdm(range(0, len(targets), batch_size), desc="evaluate", leave=False):
        past, nxt = gather_transitions(frames_NHWC, targets[i: i + batch_size], cfg.stride, cfg.num_past_frames,
                                       device)
        ids = model.infer_actions(past, nxt)
        random_ids = torch.randint(0, cfg.codebook_size, ids.shape, generator=gen).to(device)
        sums["psnr_inferred"] += psnr(model.decode_with_actions(past, ids), nxt, FRAME_RANGE).sum().item()
        sums["psnr_random"] += psnr(model.decode_with_actions(past, random_ids), nxt, FRAME_RANGE).sum().item()
        sums["psnr_copy_last"] += psnr(past[:, -1], nxt, FRAME_RANGE).sum().item()
        codes.append(ids.cpu())
    codes = torch.cat(codes)
    metrics = {k: v / len(targets) for k, v in sums.items()}
    metrics["delta_psnr"] = metrics["psnr_inferred"] - metrics["psnr_random"]
    perplexity, used = code_usage(codes, cfg.codebook_size)
    metrics.update(perplexity=perplexity.item(), codes_used_fraction=used.item(),
                   code_histogram=torch.bincount(codes, minlength=cfg.codebook_size).tolist(),
                   num_val_transitions=len(targets))
    return metrics


def probe_metrics(model: LAM, train: dict, train_frames: torch.Tensor, train_targets: np.ndarray, val: dict,
                  val_frames: torch.Tensor, val_targets: np.ndarray, batch_size: int, device) -> dict:
    """Action probe (lam/probe.py) of the latent actions against the true button combinations."""
    stride = model.config.stride
    train_labels = transition_labels(train["buttons"], train_targets, stride)
    val_labels = transition_labels(val["buttons"], val_targets, stride)
    train_codes = infer_codes(model, train_frames, train_targets, batch_size, device, "probe: train codes")
    val_codes = infer_codes(model, val_frames, val_targets, batch_size, device, "probe: val codes")
    result = action_probe(train_codes, train_labels, val_codes, val_labels)
    names = train["button_names"] or [f"button{b}" for b in range(train["buttons"].shape[1])]
    return {"action_probe_acc": result["probe_acc"], "action_majority_rate": result["majority_rate"],
            "action_train_majority_rate": result["train_majority_rate"],
            "action_probe_mapping": {str(c): combination_name(label, names) for c, label in result["mapping"].items()},
            "action_label": "most frequent button combination over the transition's raw tics"}


def train(args) -> dict:
    apply_cpu_settings(args.num_threads)
    device = resolve_device(args.device)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    train_data = load_frames_npz(args.train_data)
    val_data = load_frames_npz(args.val_data)
    cfg = build_config(args, train_data["frames"])
    if val_data["frames"].shape[1:] != train_data["frames"].shape[1:]:
        raise DataMismatchError(f"{args.val_data}: frames {val_data['frames'].shape[1:]} differ from "
                                f"{args.train_data}: {train_data['frames'].shape[1:]}")
    gap = cfg.stride * cfg.num_past_frames
    train_targets = valid_targets(train_data["segment_ids"], gap)
    val_targets = valid_targets(val_data["segment_ids"], gap)
    for path, targets in ((args.train_data, train_targets), (args.val_data, val_targets)):
        if len(targets) == 0:
            raise DataMismatchError(f"{path}: no segment is longer than {gap} frames (stride {cfg.stride} x "
                                    f"{cfg.num_past_frames} past frames), so there is no transition to learn from")
    train_frames = torch.from_numpy(train_data["frames"])
    val_frames = torch.from_numpy(val_data["frames"])
    logger.info("%d train / %d val transitions, config %s", len(train_targets), len(val_targets), cfg.to_dict())

    model = LAM(cfg).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.learning_rate, weight_decay=args.weight_decay,
                                  fused=device.type == "cuda")
    # linear warmup, then cosine decay to 10 % (train.py's --lr_scheduler_type custom_cosine)
    schedule = lr_multiplier("custom_cosine", args.warmup_steps, args.max_train_steps)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    output_dir = Path(args.output_dir)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda")
    model.train()
    start = time.time()
    bar = tqdm(range(1, args.max_train_steps + 1), desc="train LAM")
    for step in bar:
        past, nxt = gather_transitions(train_frames, rng.choice(train_targets, args.batch_size), cfg.stride,
                                       cfg.num_past_frames, device)
        with autocast:
            out = model(past, nxt)
        optimizer.zero_grad(set_to_none=True)
        out.loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
        optimizer.step()
        scheduler.step()
        bar.set_postfix(recon_psnr=f"{10 * math.log10(4 / max(out.recon_loss.item(), 1e-10)):.2f}",
                        perplexity=f"{out.perplexity.item():.2f}", restarted=out.num_restarted)
        if args.checkpointing_steps and step % args.checkpointing_steps == 0 and step < args.max_train_steps:
            model.save_pretrained(output_dir / "checkpoint")
    train_seconds = time.time() - start
    model.eval()
    model.save_pretrained(output_dir)

    metrics = {"train_steps": args.max_train_steps, "train_seconds": round(train_seconds, 1)}
    metrics.update(evaluate(model, val_frames, evenly_spaced(val_targets, args.max_eval_examples),
                            args.eval_batch_size, device, args.seed))
    if train_data["buttons"] is not None and val_data["buttons"] is not None:
        probe_train = train_targets
        if 0 < args.max_probe_train_examples < len(train_targets):
            probe_train = np.sort(rng.choice(train_targets, args.max_probe_train_examples, replace=False))
        metrics.update(probe_metrics(model, train_data, train_frames, probe_train, val_data, val_frames,
                                     evenly_spaced(val_targets, args.max_eval_examples), args.eval_batch_size,
                                     device))
    else:
        logger.warning("no 'actions_buttons' in the data: skipping the action probe")
    write_json_atomic(output_dir / "metrics.json", metrics, "the LAM metrics")
    return metrics


def main(argv=None):
    setup_logging()
    print(json.dumps(train(parse_args(argv))))


if __name__ == "__main__":
    sys.exit(run_main("lam.train", main))
