#!/usr/bin/env python
"""The 1X challenge evaluator (docs/formats.md §5): temporally teacher-forced CE, token accuracy, LPIPS, s/frame;
or, with --protocol rollout, the 1X sampling challenge's free-running rollout scored in pixels.

    ./evaluate.py --val_data_dir data/val_v1.1 --checkpoint_dir 1x-technologies/GENIE_35M
    ./evaluate.py --protocol rollout --num_prompt_frames 8 --max_examples 48
    ./evaluate.py --protocol copy_ceiling --ceiling_block 8 --max_examples 48 --spread_examples

Teacher-forced protocol (the default). Each validation window (16 frames at stride 15, non-overlapping) is
predicted frame by frame from ground-truth prefixes with MaskGIT; the model's temporal KV cache computes the
ground-truth context once and all 15 targets in one batched pass per MaskGIT step. Progress goes to stderr; the
last line printed on stdout is one JSON object with loss, acc, copy_acc (the accuracy of copying ground-truth frame
t-1 on the same windows, the baseline acc must beat), bit_err, pred_bit_err and copy_bit_err (wrong bits of a
token id per target token: expected of a token drawn from the prediction, of the protocol's own predictions, of
copying frame t-1; a token a few bits off decodes close to the right one; null for a vocabulary that is not a power
of two), pred_lpips (null with --skip_lpips), gen_time, dec_time (s per frame; null when nothing is decoded) and
num_examples. Evaluation (either protocol) runs in one
process on one device: launched with WORLD_SIZE > 1 it exits with an error.

Action-conditioned checkpoints (genie/actions.py) read their action streams from the dataset's actions/ and follow
the challenge's rule: target frame t sees the actions of frames < t only (so with latent actions, the latent
action of the transition into t, inferred from frame t itself, is not given). A checkpoint with latent actions
adds these keys:
- delta_psnr (Genie's controllability metric): from each window's first num_prompt_frames frames, the remaining
  frames are generated twice, with the latent actions inferred from the ground truth and with uniformly random
  ones (same seed, same sampling noise); delta_psnr = mean PSNR(inferred, gt) - mean PSNR(random, gt) over the
  decoded generated frames (null with --skip_lpips: nothing is decoded). On a few dozen windows one draw of the
  sampling noise moves it by tenths of a dB, so --delta_psnr_seeds N repeats it with the sampler seeds --seed,
  --seed + 1, ..., --seed + N - 1 (each run exactly what --seed alone gives) and reports their mean;
  delta_psnr_runs lists the N values;
- action_probe_acc, action_majority_rate: lam/probe.py's probe of the latent action ids against the
  true button combinations (actions/buttons.bin), fitted on --train_data_dir and scored on --val_data_dir (null
  when either lacks buttons.bin or latent_action.bin).

Rollout protocol (--protocol rollout; same windows, --max_examples, --batch_size, --seed, --maskgit_steps,
--temperature and --unmask_mode). Each window's first P = --num_prompt_frames (default 8, 1 <= P < --window_size)
ground-truth frames are the prompt and the remaining T - P frames are generated free-running
(genie.inference.generate: each frame from the model's own earlier ones). Action-conditioned and latent-action
models play the window's own action rows for every frame (control, as the sampling challenge gives the future robot
states); video-only models get none, and so does any model with --withhold_actions (in both protocols; the JSON line
then carries "actions_withheld": true). Predicted and true
frames are decoded with the tokenizer (also with --skip_lpips, which then only skips LPIPS) and scored per horizon
h = 1..T-P (generated frame P + h - 1), averaged over windows; "hold" is the baseline that repeats the decoded last
prompt frame (P - 1) for every horizon. The JSON line holds only these keys (no delta_psnr or action probe):
- protocol ("rollout"), num_prompt_frames (P);
- rollout_psnr, hold_psnr: lists of T - P mean PSNRs in dB (common.images.psnr, pixels 0..255), one per horizon;
- rollout_ssim, hold_ssim: the same for SSIM (common.images.ssim: 11x11 Gaussian window, per-channel mean);
- rollout_lpips, hold_lpips: the same for AlexNet LPIPS (null with --skip_lpips);
- rollout_psnr_mean, hold_psnr_mean, rollout_ssim_mean, hold_ssim_mean, rollout_lpips_mean, hold_lpips_mean: the
  means of those lists over horizons (LPIPS ones null with --skip_lpips);
- rollout_far_psnr, hold_far_psnr: PSNR at the last horizon h = T - P (the sampling challenge's headline number);
- rollout_unchanged, true_unchanged: per horizon, the share of tokens equal to the token at the same position one
  frame earlier (at h = 1: the prompt's last frame), in the generated and in the true frames; rollout_repeated,
  true_repeated: the share equal to their left neighbour in the same frame. A rollout that freezes shows
  unchanged rising towards 1, one that flattens into uniform patches shows repeated far above the true frames';
  each with its _mean over horizons;
- maskgit_steps, temperature, copy_bias, greedy_tokens, sampled_tokens, stall_ratio: the sampler that generated
  them (a window held by the stall rule shows unchanged = 1 after the frame it stalled at);
- gen_time: seconds per generated frame (tokens only, as above); num_examples: windows evaluated.
With --per_window_out FILE (rollout and copy_ceiling) the same per-horizon lists are also written for each window
alone, one JSON line per window, with where the window lies in the dataset (window, first_frame, segment_id), so
that the scores can be split by what happens in each window (its actions, its map); the summary's lists are their
means over the file's lines.

Copy-ceiling protocol (--protocol copy_ceiling; no checkpoint is read): the rollout protocol's windows, prompt and
scores, with the generated frames replaced by the best futures made only of whole-token copies, chosen knowing the
true frames (genie/copy_ceiling.py): each token copied from a neighbour within --ceiling_radius positions in the
ceiling's own frame before, one displacement per --ceiling_block x --ceiling_block tile of positions. A diagnostic of
the previous-frame pointer: how good its copies could be. The JSON line has the rollout keys (rollout_* are the
ceiling's frames; gen_time null) without the sampler's, plus radius, block and exact_share (the share of the
ceiling's tokens that are the true ones).
"""
import argparse
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from einops import rearrange
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from common.cli import (add_device_arg, add_num_threads_arg, add_stall_ratio_arg, add_token_choice_args,
                        apply_cpu_settings, check_stall_ratio, finite_float, resolve_device, setup_logging)
from common.config import ConfigError
from common.errors import CheckpointError, DataMismatchError, WriteError, writing
from common.files import atomic_file
from common.images import psnr, ssim
from data import RawTokenDataset, TokenDatasetError, write_token_dataset
from genie.actions import LATENT_ACTION_NAME, latent_action_sidecar, prepare_action_streams, window_actions
from genie.config import check_dataset_matches
from genie.copy_ceiling import ceiling_rollout, code_distances
from genie.factorization import bits_of_power_of_two
from genie.metrics import RunningMean, factored_cross_entropy, images_to_unit_range, true_bit_probs
from genie.sampling import UNMASK_MODES
from genie.inference import changed_share, generate, teacher_forced
from genie.model import STMaskGIT
from lam.data import valid_targets
from lam.probe import action_probe, transition_labels
from magvit2 import VQModel
from magvit2.lpips import LPIPS

logger = logging.getLogger("evaluate")

DEFAULT_VAL_DIR = "data/val_v1.1"
SAMPLE_VAL_DIR = "data/sample/val"
DEFAULT_TOKENIZER = "data/magvit2.ckpt"
DEFAULT_TRAIN_DIR = "data/sample/train"
BUTTONS_NAME = "buttons"  # the sample world's true actions, labels of the latent action probe
LPIPS_CHUNK = 32  # frames per LPIPS / decoding call, bounds memory on CPU
PROTOCOLS = ("teacher_forced", "rollout", "copy_ceiling")
DEFAULT_ROLLOUT_PROMPT_FRAMES = 8


class EvaluationError(RuntimeError):
    """An evaluation that cannot be set up (several processes, no tokenizer or LPIPS weights, an output directory
    that holds something else); data that does not fit the checkpoint raises DataMismatchError."""


def default_val_data_dir() -> str:
    """data/val_v1.1, or the embedded sample world's validation split when only that exists."""
    if not Path(DEFAULT_VAL_DIR).exists() and Path(SAMPLE_VAL_DIR).exists():
        return SAMPLE_VAL_DIR
    return DEFAULT_VAL_DIR


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--protocol", choices=PROTOCOLS, default="teacher_forced",
                        help="teacher_forced: the challenge's CE / accuracy / LPIPS protocol (default); rollout: "
                             "prompt with the first --num_prompt_frames frames, generate the rest free-running, "
                             "report PSNR / SSIM / LPIPS per horizon against the hold-the-last-frame baseline; "
                             "copy_ceiling: the same scores for the best futures made only of copies of the frame "
                             "before's nearby tokens, chosen knowing the truth (no checkpoint read).")
    parser.add_argument("--ceiling_radius", type=int, default=None,
                        help="copy_ceiling only: copies come from neighbours at most this many positions away in "
                             "each direction (default 2; a pointer's copy_radius).")
    parser.add_argument("--ceiling_block", type=int, default=None,
                        help="copy_ceiling only: positions in each block x block tile share one displacement "
                             "(default 1: every position its own; the frame's side: one shift of the whole frame). "
                             "Must divide the frame's height and width in tokens.")
    parser.add_argument("--num_prompt_frames", type=int, default=None,
                        help=f"Rollout and copy_ceiling only: ground-truth prompt frames P per window, 1 <= P < "
                             f"--window_size (default {DEFAULT_ROLLOUT_PROMPT_FRAMES}); the other window_size - P are "
                             f"generated.")
    parser.add_argument("--val_data_dir", default=None,
                        help=f"Token dataset to evaluate on (default: {DEFAULT_VAL_DIR}, or {SAMPLE_VAL_DIR} when "
                             f"only that exists).")
    parser.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt",
                        help="GENIE checkpoint directory (config.json + model.safetensors) or a Hugging Face hub id "
                             "such as 1x-technologies/GENIE_35M (not read by --protocol copy_ceiling).")
    parser.add_argument("--batch_size", type=int, default=16, help="Windows per forward pass.")
    parser.add_argument("--maskgit_steps", type=int, default=2, help="MaskGIT sampling steps per frame.")
    parser.add_argument("--temperature", type=finite_float, default=0.0,
                        help="Sampling temperature (divides the logits); 0 samples greedily (argmax).")
    parser.add_argument("--copy_bias", type=finite_float, default=0.0,
                        help="Models with a copy head (copy_radius): added to every previous-frame neighbour's score "
                             "when sampling (e^bias times the copy weight). > 0 gives sharper futures closer to "
                             "the previous frame (better LPIPS, lower PSNR); 0 is the model as trained.")
    add_token_choice_args(parser)
    add_stall_ratio_arg(parser)
    parser.add_argument("--unmask_mode", choices=UNMASK_MODES, default="random",
                        help="Which tokens each MaskGIT step reveals: random (published default) or the most "
                             "confident (greedy).")
    parser.add_argument("--withhold_actions", action="store_true",
                        help="Models with action inputs: give them none (every frame gets the learned 'no action' "
                             "input that training's action dropout teaches), to measure what the model predicts "
                             "from the frames alone. The latent-action metrics (delta_psnr, probe) are skipped.")
    parser.add_argument("--per_window_out", default=None,
                        help="Rollout and copy_ceiling only: also write the scores of each window alone to this JSON "
                             "Lines file (one line per window, written when the run ends): window (its index among "
                             "the dataset's windows), first_frame (its first frame in video.bin), segment_id (when "
                             "the dataset has segment_ids.bin), and every per-horizon list of the summary "
                             "(rollout_psnr, hold_psnr, ..., true_repeated) for that window.")
    parser.add_argument("--save_outputs_dir", default=None,
                        help="Write the predictions as a token dataset in the generated layout: per window, "
                             "frame 0 | predicted frames 1..T-1 | ground truth frames 1..T-1.")
    parser.add_argument("--max_examples", type=int, default=None,
                        help="Evaluate only N validation windows (keeps CPU runs short): the first N, or N evenly "
                             "spaced over the dataset with --spread_examples.")
    parser.add_argument("--spread_examples", action="store_true",
                        help="With --max_examples: take the N windows evenly spaced over the whole dataset (every "
                             "episode and map represented) instead of the first N (the start of the first episodes).")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help="MAGVIT2 tokenizer used to decode frames for LPIPS and the rollout's PSNR / SSIM "
                             f"(default: the dataset metadata's tokenizer_ckpt, else {DEFAULT_TOKENIZER}).")
    parser.add_argument("--skip_lpips", action="store_true",
                        help="Skip LPIPS (no LPIPS weights needed). Teacher-forced: nothing is decoded (no tokenizer "
                             "needed), pred_lpips and dec_time are null. Rollout: frames are still decoded for PSNR / "
                             "SSIM, the *_lpips keys are null.")
    add_device_arg(parser)
    add_num_threads_arg(parser)
    parser.add_argument("--seed", type=int, default=0, help="Seed of the sampler's random numbers.")
    parser.add_argument("--delta_psnr_seeds", type=int, default=1,
                        help="Latent-action checkpoints: compute delta_psnr with this many sampler seeds (--seed, "
                             "--seed + 1, ...) and report the mean (delta_psnr) and every run (delta_psnr_runs). One "
                             "draw of the noise moves it by tenths of a dB on a few dozen windows.")
    parser.add_argument("--train_data_dir", default=DEFAULT_TRAIN_DIR,
                        help="Token dataset whose latent actions and buttons fit the latent action probe (checkpoints "
                             "with latent actions only).")
    parser.add_argument("--window_size", type=int, default=16, help="Frames per validation window.")
    parser.add_argument("--stride", type=int, default=15, help="Frames between a window's frames (30 Hz / 15 = 2 Hz).")
    args = parser.parse_args(argv)
    for name in ("batch_size", "maskgit_steps", "delta_psnr_seeds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.max_examples is not None and args.max_examples < 1:
        parser.error("--max_examples must be >= 1")
    if args.temperature < 0:
        parser.error("--temperature must be >= 0")
    if args.window_size < 2:
        parser.error("--window_size must be >= 2 (frame 0 is the first prompt, frames 1.. are predicted)")
    if args.protocol == "copy_ceiling":
        args.ceiling_radius = 2 if args.ceiling_radius is None else args.ceiling_radius
        args.ceiling_block = 1 if args.ceiling_block is None else args.ceiling_block
        if args.ceiling_radius < 0 or args.ceiling_block < 1:
            parser.error(f"--ceiling_radius must be >= 0 and --ceiling_block >= 1, got {args.ceiling_radius} and "
                         f"{args.ceiling_block}")
        if args.stall_ratio is not None:
            parser.error("--stall_ratio is a decoding rule for a model's futures; --protocol copy_ceiling has no model")
    elif args.ceiling_radius is not None or args.ceiling_block is not None:
        parser.error("--ceiling_radius and --ceiling_block apply to --protocol copy_ceiling only")
    if args.protocol in ("rollout", "copy_ceiling"):
        if args.num_prompt_frames is None:
            args.num_prompt_frames = DEFAULT_ROLLOUT_PROMPT_FRAMES
        if not 1 <= args.num_prompt_frames < args.window_size:
            parser.error(f"--num_prompt_frames must be in 1..{args.window_size - 1} (at least one prompt frame and "
                         f"one frame to generate in windows of --window_size {args.window_size}), got "
                         f"{args.num_prompt_frames}")
        if args.per_window_out is not None and Path(args.per_window_out).is_dir():
            parser.error(f"--per_window_out is a file to write; {args.per_window_out} is a directory")
        if args.save_outputs_dir is not None:
            parser.error(f"--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol "
                         f"{args.protocol}")
        check_stall_ratio(parser, args.stall_ratio, args.num_prompt_frames)
    else:
        if args.num_prompt_frames is not None:
            parser.error("--num_prompt_frames applies to --protocol rollout and copy_ceiling only")
        if args.per_window_out is not None:
            parser.error("--per_window_out applies to --protocol rollout and copy_ceiling only (the teacher-forced "
                         "protocol's predictions: --save_outputs_dir)")
    if args.val_data_dir is None:
        args.val_data_dir = default_val_data_dir()
    return args


class FrameScorer:
    """Decodes token frames with the MAGVIT2 tokenizer and scores predictions with AlexNet LPIPS (with_lpips=False:
    decoding only, no LPIPS weights needed)."""

    def __init__(self, tokenizer_ckpt: str, device: torch.device, with_lpips: bool = True):
        self.tokenizer = VQModel.from_checkpoint(tokenizer_ckpt, map_location=device).eval()
        self.lpips = LPIPS().to(device) if with_lpips else None

    def decode(self, tokens_NHW: torch.Tensor) -> torch.Tensor:
        """(N, h, w) token ids -> uint8 images (N, H, W, 3)."""
        return self.tokenizer.tokens_to_images(tokens_NHW)

    def lpips_distances(self, images_a: torch.Tensor, images_b: torch.Tensor) -> torch.Tensor:
        """uint8 (N, H, W, 3) pairs -> (N,) LPIPS distances, pixels scaled to [-1, 1]."""
        return self.lpips(images_to_unit_range(images_a), images_to_unit_range(images_b))


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def batch_actions(model: STMaskGIT, batch: dict, device: torch.device, args: argparse.Namespace):
    """(real actions (B, T, D) or None, latent ids (B, T) or None) of a loader batch, for the model's inputs."""
    if not model.config.uses_actions or args.withhold_actions:
        return None, None
    actions_BTD, latent_BT = window_actions(model.config, batch["actions"], where=f"{args.val_data_dir}/actions")
    return (None if actions_BTD is None else actions_BTD.to(device),
            None if latent_BT is None else latent_BT.to(device))


TEACHER_FORCED_KEYS = ("loss", "acc", "copy_acc", "bit_err", "pred_bit_err", "copy_bit_err", "pred_lpips", "gen_time",
                       "dec_time")


def evaluate(model: STMaskGIT, loader, args: argparse.Namespace, device: torch.device,
             scorer: Optional[FrameScorer] = None, outputs: Optional[list] = None) -> dict:
    """Run the teacher-forced protocol over `loader`; return the metrics dict (the JSON line's content).

    outputs: when a list, per-window frames (prompt | predictions | ground truth) are appended to it as numpy.
    """
    metrics = {name: RunningMean() for name in TEACHER_FORCED_KEYS}
    num_bits = bits_of_power_of_two(model.config.image_vocab_size)
    generator = torch.Generator(device=device).manual_seed(args.seed)
    autocast = (torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda"
                else contextlib.nullcontext())
    num_examples = 0
    progress = tqdm(loader, desc="evaluate", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        targets_BTHW = x_BTHW[:, 1:]
        actions_BTD, latent_BT = batch_actions(model, batch, device, args)

        _synchronize(device)
        start = time.perf_counter()
        with autocast:
            samples_BTHW, logits_BVFTHW = teacher_forced(model, x_BTHW, args.maskgit_steps, args.temperature,
                                                         args.unmask_mode, generator=generator,
                                                         actions=actions_BTD, latent_actions=latent_BT)
        _synchronize(device)
        metrics["gen_time"].update(time.perf_counter() - start, B * (T - 1))

        metrics["loss"].update(factored_cross_entropy(logits_BVFTHW, targets_BTHW).sum().item(), targets_BTHW.numel())
        metrics["acc"].update((samples_BTHW == targets_BTHW).sum().item(), targets_BTHW.numel())
        metrics["copy_acc"].update((x_BTHW[:, :-1] == targets_BTHW).sum().item(), targets_BTHW.numel())
        if num_bits:
            add_bit_errors(metrics, logits_BVFTHW, samples_BTHW, x_BTHW[:, :-1], targets_BTHW, num_bits)
        if scorer is not None:
            score_frames(scorer, samples_BTHW.flatten(0, 1), targets_BTHW.flatten(0, 1), metrics, device)
        if outputs is not None:
            outputs.append(torch.cat([x_BTHW[:, :1], samples_BTHW, targets_BTHW], dim=1).cpu().numpy())
        num_examples += B
        progress.set_postfix({name: f"{m.mean:.4g}" for name, m in metrics.items() if m.mean is not None})

    result = {name: metrics[name].mean for name in TEACHER_FORCED_KEYS}
    result["num_examples"] = num_examples
    return result


def add_bit_errors(metrics: dict, logits_BVFTHW: torch.Tensor, samples_BTHW: torch.Tensor, copies_BTHW: torch.Tensor,
                   targets_BTHW: torch.Tensor, num_bits: int) -> None:
    """Wrong bits per token: expected of a token drawn from the prediction (bit_err), of the evaluation's own
    predictions (pred_bit_err) and of copying frame t-1 (copy_bit_err). Tokens a few bits apart decode alike."""
    n = targets_BTHW.numel()
    logits_NVF = rearrange(logits_BVFTHW, "B V F T H W -> (B T H W) V F")
    metrics["bit_err"].update((1 - true_bit_probs(logits_NVF, targets_BTHW.flatten())).sum().item(), n)
    metrics["pred_bit_err"].update(code_distances(samples_BTHW, targets_BTHW, num_bits).sum().item(), n)
    metrics["copy_bit_err"].update(code_distances(copies_BTHW, targets_BTHW, num_bits).sum().item(), n)


def score_frames(scorer: FrameScorer, pred_NHW: torch.Tensor, gt_NHW: torch.Tensor, metrics: dict,
                 device: torch.device) -> None:
    """Decode predicted and ground-truth frames (timing the predictions' decoding) and add their LPIPS."""
    for a in range(0, len(pred_NHW), LPIPS_CHUNK):
        _synchronize(device)
        start = time.perf_counter()
        pred_images = scorer.decode(pred_NHW[a:a + LPIPS_CHUNK])
        _synchronize(device)
        metrics["dec_time"].update(time.perf_counter() - start, len(pred_images))
        gt_images = scorer.decode(gt_NHW[a:a + LPIPS_CHUNK])
        metrics["pred_lpips"].update(scorer.lpips_distances(pred_images, gt_images).sum().item(), len(pred_images))


def decode_frames(scorer: FrameScorer, tokens_NHW: torch.Tensor) -> torch.Tensor:
    """(N, h, w) token ids -> uint8 images (N, H, W, 3), decoded LPIPS_CHUNK frames at a time."""
    return torch.cat([scorer.decode(tokens_NHW[a:a + LPIPS_CHUNK]) for a in range(0, len(tokens_NHW), LPIPS_CHUNK)])


def image_scores(scorer: FrameScorer, images_NhHW3: torch.Tensor, truth_NhHW3: torch.Tensor,
                 with_lpips: bool) -> dict:
    """{"psnr", "ssim"[, "lpips"]: (N, h)} of uint8 images (N, h, H, W, 3) against the true ones (same shape),
    computed LPIPS_CHUNK frames at a time (SSIM's float64 maps of 256x256 frames are large)."""
    N, h = images_NhHW3.shape[:2]
    images_MHW3, truth_MHW3 = images_NhHW3.flatten(0, 1), truth_NhHW3.flatten(0, 1)
    chunks = {"psnr": [], "ssim": [], "lpips": []} if with_lpips else {"psnr": [], "ssim": []}
    for a in range(0, len(images_MHW3), LPIPS_CHUNK):
        pred, true = images_MHW3[a:a + LPIPS_CHUNK], truth_MHW3[a:a + LPIPS_CHUNK]
        chunks["psnr"].append(psnr(pred, true, value_range=(0.0, 255.0)))
        chunks["ssim"].append(ssim(pred, true))
        if with_lpips:
            chunks["lpips"].append(scorer.lpips_distances(pred, true))
    return {metric: torch.cat(values).float().view(N, h) for metric, values in chunks.items()}


def score_rollout(scorer: FrameScorer, pred_NhHW: torch.Tensor, last_NHW: torch.Tensor, future_NhHW: torch.Tensor,
                  with_lpips: bool) -> dict:
    """Per-window, per-horizon scores of generated frames and of the hold baseline, in pixels.

    pred_NhHW: generated token frames (N, h, H, W), h = T - P horizons; last_NHW: the prompt's last token frame
    (N, H, W); future_NhHW: the true token frames the prediction replaces (N, h, H, W).
    Returns {"rollout_psnr", "hold_psnr", "rollout_ssim", "hold_ssim"[, "rollout_lpips", "hold_lpips"]: (N, h)}.
    """
    N, h = pred_NhHW.shape[:2]
    truth_NhHW3 = decode_frames(scorer, future_NhHW.flatten(0, 1)).unflatten(0, (N, h))
    pred_NhHW3 = decode_frames(scorer, pred_NhHW.flatten(0, 1)).unflatten(0, (N, h))
    hold_NHW3 = decode_frames(scorer, last_NHW)  # decoded once per window, repeated over the horizons
    hold_NhHW3 = hold_NHW3.unsqueeze(1).expand(-1, h, -1, -1, -1)
    scores = {}
    for name, images_NhHW3 in (("rollout", pred_NhHW3), ("hold", hold_NhHW3)):
        for metric, values_Nh in image_scores(scorer, images_NhHW3, truth_NhHW3, with_lpips).items():
            scores[f"{name}_{metric}"] = values_Nh
    return scores


def token_statistics(pred_NhHW: torch.Tensor, last_NHW: torch.Tensor, future_NhHW: torch.Tensor) -> dict:
    """Per-window, per-horizon token statistics (N, h) of the generated and the true frames (module doc):
    {"rollout_unchanged", "true_unchanged", "rollout_repeated", "true_repeated"}. Shapes as `score_rollout`."""
    stats = {}
    for name, frames_NhHW in (("rollout", pred_NhHW), ("true", future_NhHW)):
        before_NhHW = torch.cat([last_NHW.unsqueeze(1), frames_NhHW[:, :-1]], dim=1)
        stats[f"{name}_unchanged"] = 1 - changed_share(frames_NhHW, before_NhHW)
        stats[f"{name}_repeated"] = (frames_NhHW[..., 1:] == frames_NhHW[..., :-1]).float().mean(dim=(2, 3))
    return stats


def add_rollout_scores(sums: dict, scorer: FrameScorer, tokens_BTHW: torch.Tensor, x_BTHW: torch.Tensor, P: int,
                       with_lpips: bool, per_window: Optional[list] = None) -> None:
    """Add the per-horizon scores and token statistics of generated windows (B, T, H, W) against the true ones
    (frames P.. generated, frame P - 1 held) to sums {key: (h,) summed over windows}, in place; with a list
    `per_window`, also append each window's own {key: [h floats]}."""
    scores = score_rollout(scorer, tokens_BTHW[:, P:], x_BTHW[:, P - 1], x_BTHW[:, P:], with_lpips)
    scores.update(token_statistics(tokens_BTHW[:, P:], x_BTHW[:, P - 1], x_BTHW[:, P:]))
    for key, values_Bh in scores.items():
        sums[key] = sums.get(key, 0) + values_Bh.double().sum(dim=0).cpu()
    if per_window is not None:
        lists = {key: values_Bh.double().cpu().tolist() for key, values_Bh in scores.items()}
        per_window.extend({key: lists[key][b] for key in lists} for b in range(tokens_BTHW.shape[0]))


def write_per_window(path, per_window: list, dataset: RawTokenDataset, indices: List[int]) -> None:
    """Write --per_window_out: one JSON line per evaluated window (in `indices` order, as the loader gave them),
    its place in `dataset` first, then its scores; atomically, creating the parent directory."""
    if len(per_window) != len(indices):
        raise EvaluationError(f"internal: {len(per_window)} per-window scores for {len(indices)} windows")
    lines = []
    for window, scores in zip(indices, per_window):
        first_frame = int(dataset.valid_start_inds[window])
        place = {"window": window, "first_frame": first_frame}
        if dataset.segment_ids is not None:
            place["segment_id"] = int(dataset.segment_ids[first_frame])
        lines.append(json.dumps({**place, **scores}))
    path = Path(path)
    with writing("the per-window scores", path):
        path.parent.mkdir(parents=True, exist_ok=True)
    atomic_file(path, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"), "the per-window scores")


def rollout_result(sums: dict, num_examples: int, num_prompt_frames: int, gen_time: Optional[float]) -> dict:
    """The rollout JSON line (module doc) from per-horizon score sums {"rollout_psnr": (h,), ...} over windows."""
    result = {"protocol": "rollout", "num_prompt_frames": num_prompt_frames}
    keys = [f"{name}_{metric}" for metric in ("psnr", "ssim", "lpips") for name in ("rollout", "hold")]
    keys += [f"{name}_{stat}" for stat in ("unchanged", "repeated") for name in ("rollout", "true")]  # token_statistics
    for key in keys:  # LPIPS is missing from the sums with --skip_lpips
        result[key] = (sums[key] / num_examples).tolist() if key in sums and num_examples else None
    for key in keys:
        result[f"{key}_mean"] = None if result[key] is None else sum(result[key]) / len(result[key])
    for name in ("rollout", "hold"):
        result[f"{name}_far_psnr"] = None if result[f"{name}_psnr"] is None else result[f"{name}_psnr"][-1]
    result["gen_time"] = gen_time
    result["num_examples"] = num_examples
    return result


@torch.no_grad()
def rollout_evaluate(model: STMaskGIT, loader, args: argparse.Namespace, device: torch.device,
                     scorer: FrameScorer, per_window: Optional[list] = None) -> dict:
    """Run the rollout protocol over `loader` (module doc); return the metrics dict (the JSON line's content).
    per_window: when a list, each window's own scores are appended to it (`add_rollout_scores`)."""
    P = args.num_prompt_frames
    with_lpips = not args.skip_lpips
    generator = torch.Generator(device=device).manual_seed(args.seed)
    autocast = (torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda"
                else contextlib.nullcontext())
    gen_time, sums, num_examples = RunningMean(), {}, 0
    progress = tqdm(loader, desc="rollout", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        # every row of the window is played: the sampling challenge gives the future actions (robot states)
        actions_BTD, latent_BT = batch_actions(model, batch, device, args)

        _synchronize(device)
        start = time.perf_counter()
        with autocast:
            tokens_BTHW, _ = generate(model, x_BTHW[:, :P], T - P, args.maskgit_steps, args.temperature,
                                      args.unmask_mode, generator=generator, actions=actions_BTD,
                                      latent_actions=latent_BT, control=True, stall_ratio=args.stall_ratio)
        _synchronize(device)
        gen_time.update(time.perf_counter() - start, B * (T - P))

        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window)
        num_examples += B
        progress.set_postfix({"psnr": f"{sums['rollout_psnr'].mean().item() / num_examples:.4g}",
                              "hold": f"{sums['hold_psnr'].mean().item() / num_examples:.4g}"})
    return {**rollout_result(sums, num_examples, P, gen_time.mean), "maskgit_steps": args.maskgit_steps,
            "temperature": args.temperature, "copy_bias": args.copy_bias, "greedy_tokens": args.greedy_tokens,
            "sampled_tokens": args.sampled_tokens, "stall_ratio": args.stall_ratio}


@torch.no_grad()
def copy_ceiling_evaluate(loader, args: argparse.Namespace, device: torch.device, scorer: FrameScorer,
                          num_bits: int, per_window: Optional[list] = None) -> dict:
    """The copy-ceiling protocol over `loader` (module doc): the rollout protocol's scores of
    genie.copy_ceiling.ceiling_rollout's frames (each window's own appended to `per_window` when a list)."""
    P, with_lpips = args.num_prompt_frames, not args.skip_lpips
    sums, num_examples, exact, num_tokens = {}, 0, 0, 0
    for batch in tqdm(loader, desc="copy ceiling", unit="batch", file=sys.stderr):
        x_BTHW = batch["tokens"].to(device).long()
        tokens_BTHW, exact_B = ceiling_rollout(x_BTHW, P, args.ceiling_radius, args.ceiling_block, num_bits)
        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window)
        num_examples += x_BTHW.shape[0]
        exact += int(exact_B.sum())
        num_tokens += tokens_BTHW[:, P:].numel()
    result = rollout_result(sums, num_examples, P, None)
    return {**result, "protocol": "copy_ceiling", "radius": args.ceiling_radius, "block": args.ceiling_block,
            "exact_share": exact / max(num_tokens, 1)}


def run_copy_ceiling(args: argparse.Namespace, device: torch.device) -> dict:
    """--protocol copy_ceiling: no model; the windows of --val_data_dir as the rollout protocol picks them."""
    dataset = RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride,
                              filter_overlaps=True)
    h, w = dataset.metadata["h"], dataset.metadata["w"]
    if h % args.ceiling_block or w % args.ceiling_block:
        raise EvaluationError(f"--ceiling_block {args.ceiling_block} does not divide the {h} x {w} token frames of "
                              f"{args.val_data_dir}")
    indices = example_indices(len(dataset), args.max_examples, args.spread_examples)
    loader = DataLoader(Subset(dataset, indices), batch_size=args.batch_size, shuffle=False)
    logger.info("copy ceiling of %d windows of %s (radius %d, block %d)", len(indices), args.val_data_dir,
                args.ceiling_radius, args.ceiling_block)
    num_bits = (int(dataset.metadata["vocab_size"]) - 1).bit_length()
    per_window = [] if args.per_window_out else None
    result = copy_ceiling_evaluate(loader, args, device, frame_scorer(args, dataset, device), num_bits, per_window)
    if per_window is not None:
        write_per_window(args.per_window_out, per_window, dataset, indices)
    return result


@torch.no_grad()
def delta_psnr(model: STMaskGIT, loader, args: argparse.Namespace, device: torch.device,
               scorer: FrameScorer, seeds: List[int]) -> List[float]:
    """Genie's delta-PSNR: mean PSNR of frames generated with the ground truth's latent actions minus that with
    uniformly random latent actions, over the frames after the config's num_prompt_frames (see the module doc).
    Real action inputs, if the model also has them, stay prompt-only in both runs. One value per sampler seed (the
    random latent actions draw from seed + 1), each what that seed alone gives; the windows are read and their true
    frames decoded once for all seeds."""
    P, K = model.config.num_prompt_frames, model.config.num_latent_actions
    if P >= args.window_size:
        raise DataMismatchError(f"delta_psnr: the checkpoint's num_prompt_frames {P} leaves no frame to generate in "
                              f"windows of {args.window_size} frames")
    if args.stall_ratio is not None and P < 2:
        raise DataMismatchError(f"delta_psnr with --stall_ratio: the checkpoint's num_prompt_frames {P} gives no "
                                f"prompt motion to compare with (needs >= 2)")
    kwargs = dict(maskgit_steps=args.maskgit_steps, temperature=args.temperature, unmask_mode=args.unmask_mode,
                  control=True, stall_ratio=args.stall_ratio)
    # per seed, the same sampling noise in both runs: only the latent actions differ
    generators = [[torch.Generator(device=device).manual_seed(seed) for _ in range(2)] for seed in seeds]
    random_actions = [torch.Generator().manual_seed(seed + 1) for seed in seeds]
    psnrs = [[RunningMean(), RunningMean()] for _ in seeds]
    autocast = (torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda"
                else contextlib.nullcontext())
    for batch in tqdm(loader, desc="delta_psnr", unit="batch", file=sys.stderr):
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        actions_BTD, latent_BT = batch_actions(model, batch, device, args)
        if actions_BTD is not None:
            actions_BTD = actions_BTD.clone()
            actions_BTD[:, P:] = float("nan")  # unknown after the prompt
        truth_NHW3 = decode_frames(scorer, x_BTHW[:, P:].flatten(0, 1))
        for seed_generators, seed_random_actions, seed_psnrs in zip(generators, random_actions, psnrs):
            random_BT = latent_BT.clone()
            random_BT[:, P:] = torch.randint(0, K, (B, T - P), generator=seed_random_actions).to(device)
            for played_BT, generator, mean in zip((latent_BT, random_BT), seed_generators, seed_psnrs):
                with autocast:
                    tokens_BTHW, _ = generate(model, x_BTHW[:, :P], T - P, generator=generator,
                                              actions=actions_BTD, latent_actions=played_BT, **kwargs)
                frame_psnr = psnr(decode_frames(scorer, tokens_BTHW[:, P:].flatten(0, 1)), truth_NHW3,
                                  value_range=(0.0, 255.0))
                mean.update(frame_psnr.sum().item(), len(frame_psnr))
    return [inferred.mean - random.mean for inferred, random in psnrs]


def probe_examples(dataset: RawTokenDataset, default_stride: int):
    """(latent action ids, true button-combination labels) of the transitions with a LAM-inferred id, or None when
    the dataset lacks buttons.bin or latent_action.bin. The transition stride and LAM context come from
    actions/latent_action.json (lam/label.py), else --stride and one past frame."""
    if BUTTONS_NAME not in dataset.actions or LATENT_ACTION_NAME not in dataset.actions:
        logger.warning("%s: no actions/%s.bin or actions/%s.bin: the latent action probe is skipped",
                       dataset.data_dir, BUTTONS_NAME, LATENT_ACTION_NAME)
        return None
    sidecar = latent_action_sidecar(dataset)
    stride = int(sidecar.get("latent_action_stride", default_stride))
    num_past = int(sidecar.get("latent_action_num_past_frames", 1))
    segment_ids = (np.asarray(dataset.segment_ids) if dataset.segment_ids is not None
                   else np.zeros(dataset.metadata["num_images"], dtype=np.int64))
    targets = valid_targets(segment_ids, stride * num_past)
    codes = np.asarray(dataset.actions[LATENT_ACTION_NAME][:, 0])[targets].round().astype(np.int64)
    labels = transition_labels(np.asarray(dataset.actions[BUTTONS_NAME]), targets, stride)
    return codes, labels


def latent_action_probe(val_ds: RawTokenDataset, train_data_dir, stride: int) -> dict:
    """action_probe_acc and action_majority_rate (None when a split lacks the files)."""
    none = {"action_probe_acc": None, "action_majority_rate": None}
    if not Path(train_data_dir).is_dir():
        logger.warning("--train_data_dir %s not found: the latent action probe is skipped", train_data_dir)
        return none
    train_ds = RawTokenDataset(train_data_dir, window_size=1, filter_interrupts=False, check_tokens=False)
    train, val = probe_examples(train_ds, stride), probe_examples(val_ds, stride)
    if train is None or val is None or not len(train[0]) or not len(val[0]):
        return none
    result = action_probe(train[0], train[1], val[0], val[1])
    return {"action_probe_acc": result["probe_acc"], "action_majority_rate": result["majority_rate"]}


def save_outputs(out_dir: str, windows: list, dataset, window_size: int) -> None:
    """Write evaluated windows in the generated layout (docs/formats.md §1), one segment id per window."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        meta_path = out / "metadata.json"
        previous = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        if "num_prompt_frames" not in previous:
            raise EvaluationError(f"--save_outputs_dir {out} exists and does not hold earlier outputs (no "
                                  f"num_prompt_frames in its metadata.json); choose a new or empty directory")
    video_WFHW = np.concatenate(windows)
    frames_per_window = video_WFHW.shape[1]
    segment_ids = np.repeat(np.arange(len(video_WFHW), dtype=np.int32), frames_per_window)
    keep = {k: v for k, v in dataset.metadata.items() if k in ("token_dtype", "vocab_size", "hz", "tokenizer_ckpt")}
    write_token_dataset(out, video_WFHW.reshape(-1, *video_WFHW.shape[2:]), segment_ids=segment_ids,
                        metadata={**keep, "num_prompt_frames": 1, "window_size": window_size,
                                  "num_examples": len(video_WFHW)}, overwrite=True)


def frame_scorer(args: argparse.Namespace, dataset: RawTokenDataset, device: torch.device) -> FrameScorer:
    """The FrameScorer of --tokenizer_ckpt, else the dataset metadata's tokenizer, else DEFAULT_TOKENIZER; with
    LPIPS unless --skip_lpips."""
    tokenizer_ckpt = args.tokenizer_ckpt or dataset.metadata.get("tokenizer_ckpt") or DEFAULT_TOKENIZER
    try:
        return FrameScorer(tokenizer_ckpt, device, with_lpips=not args.skip_lpips)
    except (FileNotFoundError, ValueError) as e:  # missing tokenizer / LPIPS weights, unreadable checkpoint
        if args.protocol != "teacher_forced":
            raise EvaluationError(f"cannot set up decoding{'' if args.skip_lpips else ' + LPIPS'}: {e}\nThe "
                                  f"{args.protocol} protocol decodes frames for PSNR and SSIM: pass --tokenizer_ckpt "
                                  f"(and --skip_lpips to go without LPIPS weights).") from None
        raise EvaluationError(f"cannot set up decoding + LPIPS: {e}\nPass --skip_lpips to evaluate without "
                              f"decoding frames.") from None


def example_indices(num_windows: int, max_examples: Optional[int], spread: bool) -> List[int]:
    """Which windows to evaluate: all, the first max_examples, or (spread) max_examples evenly spaced ones."""
    if max_examples is None or max_examples >= num_windows:
        return list(range(num_windows))
    if not spread:
        return list(range(max_examples))
    return [i * num_windows // max_examples for i in range(max_examples)]


def run(args: argparse.Namespace) -> dict:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1:
        raise EvaluationError(f"evaluation runs in a single process, but WORLD_SIZE={world_size}: launch it with "
                              f"plain `python evaluate.py` (not torchrun / accelerate launch with several processes)")
    device = resolve_device(args.device)
    apply_cpu_settings(args.num_threads)
    torch.manual_seed(args.seed)
    if args.protocol == "copy_ceiling":
        return run_copy_ceiling(args, device)

    model = STMaskGIT.from_pretrained(args.checkpoint_dir).to(device).eval()
    if args.copy_bias and model.copy_head is None:
        raise DataMismatchError(f"--copy_bias: the checkpoint {args.checkpoint_dir} has no copy head (copy_radius)")
    model.set_copy_bias(args.copy_bias)
    model.set_greedy_tokens(args.greedy_tokens)
    model.set_joint_sampling(args.sampled_tokens == "joint")
    dataset = RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride,
                              filter_overlaps=True)
    check_dataset_matches(model.config, dataset, args.window_size, f"checkpoint {args.checkpoint_dir}",
                          exact_window=False)
    if model.config.uses_actions and not args.withhold_actions:
        prepare_action_streams(model.config, dataset)
    indices = example_indices(len(dataset), args.max_examples, args.spread_examples)
    num_windows = len(indices)
    loader = DataLoader(Subset(dataset, indices), batch_size=args.batch_size, shuffle=False)
    logger.info("evaluating %d windows of %s with %s on %s", num_windows, args.val_data_dir, args.checkpoint_dir,
                device)

    if args.protocol == "rollout":
        per_window = [] if args.per_window_out else None
        result = rollout_evaluate(model, loader, args, device, frame_scorer(args, dataset, device), per_window)
        if per_window is not None:
            write_per_window(args.per_window_out, per_window, dataset, indices)
    else:
        result = teacher_forced_result(model, loader, dataset, args, device)
    return {**result, "actions_withheld": True} if args.withhold_actions else result


def teacher_forced_result(model: STMaskGIT, loader, dataset: RawTokenDataset, args: argparse.Namespace,
                          device: torch.device) -> dict:
    """The teacher-forced protocol's metrics, plus the latent-action metrics for models that have them."""
    scorer = None if args.skip_lpips else frame_scorer(args, dataset, device)
    outputs = [] if args.save_outputs_dir else None
    with torch.no_grad():
        result = evaluate(model, loader, args, device, scorer, outputs)
        if model.config.num_latent_actions and not args.withhold_actions:
            if scorer is None:
                logger.warning("--skip_lpips: nothing is decoded, so delta_psnr is null")
            seeds = [args.seed + i for i in range(args.delta_psnr_seeds)]
            runs = None if scorer is None else delta_psnr(model, loader, args, device, scorer, seeds)
            result["delta_psnr"] = None if runs is None else sum(runs) / len(runs)
            result["delta_psnr_runs"] = runs
            result.update(latent_action_probe(dataset, args.train_data_dir, args.stride))
    if outputs is not None:
        save_outputs(args.save_outputs_dir, outputs, dataset, args.window_size)
    return result


def main(argv=None) -> int:
    setup_logging()
    args = parse_args(argv)
    try:
        result = run(args)
    except (EvaluationError, DataMismatchError, TokenDatasetError, ConfigError, CheckpointError, FileNotFoundError,
            NotADirectoryError, WriteError) as e:
        print(f"evaluate.py: error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
