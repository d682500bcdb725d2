"""The challenge evaluator's protocols and scores, shared by evaluate.py (the two protocols) and evaluation/diagnostics.py
(the same scores of other futures: withheld actions, per-window lines, the copy ceiling).

Teacher-forced protocol (`teacher_forced_evaluate`): each window's frames 1..T-1 predicted with MaskGIT from their
ground-truth past, scored by CE, token accuracy, copy_acc (copying ground-truth frame t-1), LPIPS and s/frame.
Rollout protocol (`rollout_evaluate`): each window's first P frames prompt, the rest generated free-running,
decoded and scored per horizon in pixels (PSNR, SSIM, LPIPS) against holding the last prompt frame, plus token
statistics of a freezing or flattening rollout (`rollout_result` lists the keys). `delta_psnr` is Genie's
controllability metric of latent-action models. Nothing here reads lam/ (the latent action probe is evaluate.py's).
"""
import argparse
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from common.cli import add_device_arg, add_num_threads_arg, apply_cpu_settings, resolve_device
from common.errors import DataMismatchError, InputError, writing
from common.files import atomic_file
from common.images import psnr, ssim
from data import RawTokenDataset, write_token_dataset
from training.action_streams import prepare_action_streams, window_actions
from genie.config import check_dataset_matches
from genie.decoding import add_decoding_args, apply_decoding, check_decoding_args, decoding_settings, sampler_kwargs
from genie.inference import changed_share, generate_frames, teacher_forced
from evaluation.metrics import RunningMean, images_to_unit_range
from genie.metrics import factored_cross_entropy
from genie.model import STMaskGIT
from magvit2 import VQModel
from magvit2.lpips import LPIPS

logger = logging.getLogger("evaluation.protocols")

DEFAULT_VAL_DIR = "data/val_v1.1"
SAMPLE_VAL_DIR = "data/sample/val"
DEFAULT_CHECKPOINT = "data/genie_model/final_checkpt"
DEFAULT_TOKENIZER = "data/magvit2.ckpt"
LPIPS_CHUNK = 32  # frames per LPIPS / decoding call, bounds memory on CPU
DEFAULT_ROLLOUT_PROMPT_FRAMES = 8
PROTOCOLS = ("teacher_forced", "rollout")
TEACHER_FORCED_KEYS = ("loss", "acc", "copy_acc", "pred_lpips", "gen_time", "dec_time")


class EvaluationError(InputError):
    """An evaluation that cannot be set up (several processes, no tokenizer or LPIPS weights, an output directory
    that holds something else); data that does not fit the checkpoint raises DataMismatchError."""


# ------------------------------------------------------------------ flags
def default_val_data_dir() -> str:
    """data/val_v1.1, or the embedded sample world's validation split when only that exists."""
    if not Path(DEFAULT_VAL_DIR).exists() and Path(SAMPLE_VAL_DIR).exists():
        return SAMPLE_VAL_DIR
    return DEFAULT_VAL_DIR


def add_window_args(parser, checkpoint: bool = True) -> None:
    """The flags of every evaluation: the validation windows, frame decoding and scoring, the device; and unless
    `checkpoint` is False (a diagnostic without a model), the checkpoint, the sampler's seed and the decoding flags
    (genie/decoding.py). Check them with `check_window_args`."""
    parser.add_argument("--val_data_dir", default=None,
                        help=f"Token dataset to evaluate on (default: {DEFAULT_VAL_DIR}, or {SAMPLE_VAL_DIR} when "
                             f"only that exists).")
    if checkpoint:
        parser.add_argument("--checkpoint_dir", default=DEFAULT_CHECKPOINT,
                            help="GENIE checkpoint directory (config.json + model.safetensors) or a Hugging Face hub "
                                 "id such as 1x-technologies/GENIE_35M (default: %(default)s).")
    parser.add_argument("--window_size", type=int, default=16,
                        help="Frames per validation window, >= 2 (default: %(default)s; at most the checkpoint's T).")
    parser.add_argument("--stride", type=int, default=15,
                        help="Frames of the dataset between a window's frames (default: %(default)s: 30 Hz / 15 = "
                             "2 Hz). Windows do not overlap.")
    parser.add_argument("--max_examples", type=int, default=None,
                        help="Evaluate only N validation windows (keeps CPU runs short): the first N, or N evenly "
                             "spaced over the dataset with --spread_examples (default: all).")
    parser.add_argument("--spread_examples", action="store_true",
                        help="With --max_examples: take the N windows evenly spaced over the whole dataset (every "
                             "episode and map represented) instead of the first N (the start of the first episodes).")
    parser.add_argument("--batch_size", type=int, default=16, help="Windows per forward pass (default: %(default)s).")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help="MAGVIT2 tokenizer that decodes token frames to pixels for LPIPS, PSNR and SSIM "
                             f"(default: the dataset metadata's tokenizer_ckpt, else {DEFAULT_TOKENIZER}).")
    parser.add_argument("--skip_lpips", action="store_true",
                        help="Skip LPIPS (no LPIPS weights needed): the LPIPS keys are null. Teacher-forced: nothing "
                             "is decoded either (no tokenizer needed; dec_time null). Rollout (and the "
                             "diagnostics that score futures): frames are still decoded for PSNR / SSIM.")
    add_device_arg(parser)
    add_num_threads_arg(parser)
    if checkpoint:
        parser.add_argument("--seed", type=int, default=0,
                            help="Seed of the sampler's random numbers (default: %(default)s).")
        add_decoding_args(parser)
    else:  # nothing random to seed
        parser.set_defaults(seed=0)


def add_protocol_args(parser, more: Tuple[str, ...] = (), more_help: str = "") -> None:
    """--protocol (teacher_forced or rollout, and the protocols `more` that `more_help` describes) and
    --num_prompt_frames (rollout only); check with `check_protocol_args`."""
    parser.add_argument("--protocol", choices=PROTOCOLS + tuple(more), default=PROTOCOLS[0],
                        help="teacher_forced (default): each frame predicted from the ground-truth frames before it, "
                             "scored by CE, token accuracy, LPIPS and s/frame; rollout: prompt with the first "
                             "--num_prompt_frames frames of each window, generate the rest free-running, score PSNR "
                             "/ SSIM / LPIPS per horizon against holding the last prompt frame" + more_help + ".")
    add_prompt_arg(parser, "Rollout protocol only: ")


def add_prompt_arg(parser, applies: str = "") -> None:
    """--num_prompt_frames of the free-running futures (default None: `check_prompt_arg` sets it)."""
    parser.add_argument("--num_prompt_frames", type=int, default=None,
                        help=f"{applies}ground-truth prompt frames P per window, 1 <= P < --window_size (default "
                             f"{DEFAULT_ROLLOUT_PROMPT_FRAMES}); the other window_size - P frames are generated.")


def add_save_outputs_arg(parser) -> None:
    parser.add_argument("--save_outputs_dir", default=None,
                        help="Teacher-forced protocol only: write the predictions as a token dataset in the generated "
                             "layout (per window: frame 0 | predicted frames 1..T-1 | ground truth frames 1..T-1).")


def add_per_window_arg(parser, applies: str = "", required: bool = False) -> None:
    parser.add_argument("--per_window_out", default=None, required=required,
                        help=f"{applies}write the scores of each window alone to this JSON Lines file (one line per "
                             f"window, written when the run ends): window (its index among the dataset's windows), "
                             f"first_frame (its first frame in video.bin), segment_id (when the dataset has "
                             f"segment_ids.bin), and every per-horizon list of the summary (rollout_psnr, hold_psnr, "
                             f"..., true_repeated) for that window; the summary's lists are their means. "
                             f"`python -m evaluation.diagnostics breakdown` groups them by the walker's motion.")


def check_window_args(parser, args: argparse.Namespace) -> None:
    """Usage errors of `add_window_args`' flags; fills in --val_data_dir's default."""
    if args.batch_size < 1:
        parser.error(f"--batch_size must be >= 1, got {args.batch_size}")
    if args.max_examples is not None and args.max_examples < 1:
        parser.error(f"--max_examples must be >= 1, got {args.max_examples}")
    if args.window_size < 2:
        parser.error("--window_size must be >= 2 (frame 0 is the first prompt, frames 1.. are predicted)")
    if args.stride < 1:
        parser.error(f"--stride must be >= 1, got {args.stride}")
    if hasattr(args, "maskgit_steps"):
        check_decoding_args(parser, args)
    if args.val_data_dir is None:
        args.val_data_dir = default_val_data_dir()


def check_prompt_arg(parser, args: argparse.Namespace) -> None:
    """--num_prompt_frames of free-running futures: its default, its range, and --stall_ratio's need of 2."""
    if args.num_prompt_frames is None:
        args.num_prompt_frames = DEFAULT_ROLLOUT_PROMPT_FRAMES
    if not 1 <= args.num_prompt_frames < args.window_size:
        parser.error(f"--num_prompt_frames must be in 1..{args.window_size - 1} (at least one prompt frame and one "
                     f"frame to generate in windows of --window_size {args.window_size}), got "
                     f"{args.num_prompt_frames}")
    if hasattr(args, "stall_ratio"):
        check_decoding_args(parser, args, args.num_prompt_frames)


def check_per_window_arg(parser, args: argparse.Namespace) -> None:
    if args.per_window_out is not None and Path(args.per_window_out).is_dir():
        parser.error(f"--per_window_out is a file to write; {args.per_window_out} is a directory")


def check_protocol_args(parser, args: argparse.Namespace) -> None:
    """Usage errors of flags that one protocol only takes (`add_protocol_args`, `add_save_outputs_arg`,
    `add_per_window_arg` where the parser has them)."""
    per_window = getattr(args, "per_window_out", None)
    if args.protocol == "policies":
        if args.save_outputs_dir is not None:
            parser.error("--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol "
                         "policies")
        return
    if args.protocol == "rollout":
        check_prompt_arg(parser, args)
        if args.save_outputs_dir is not None:
            parser.error("--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol "
                         "rollout")
        if per_window is not None:
            check_per_window_arg(parser, args)
    else:
        if args.num_prompt_frames is not None:
            parser.error("--num_prompt_frames applies to --protocol rollout only")
        if per_window is not None:
            parser.error("--per_window_out applies to --protocol rollout only (the teacher-forced protocol's "
                         "predictions: --save_outputs_dir)")


# ------------------------------------------------------------------ set-up
def start_process(args: argparse.Namespace) -> torch.device:
    """The process set-up of a command that scores futures: one process, --device, --num_threads, --seed."""
    check_single_process()
    device = resolve_device(args.device)
    apply_cpu_settings(args.num_threads)
    torch.manual_seed(args.seed)
    return device


def check_single_process() -> None:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1:
        raise EvaluationError(f"evaluation runs in a single process, but WORLD_SIZE={world_size}: launch it with "
                              f"plain `python evaluate.py` (not torchrun / accelerate launch with several processes)")


def load_model(args: argparse.Namespace, device: torch.device) -> STMaskGIT:
    """--checkpoint_dir on `device` in eval mode, decoding as the decoding flags say."""
    model = STMaskGIT.from_pretrained(args.checkpoint_dir).to(device).eval()
    apply_decoding(model, args, args.checkpoint_dir)
    return model


def example_indices(num_windows: int, max_examples: Optional[int], spread: bool) -> List[int]:
    """Which windows to evaluate: all, the first max_examples, or (spread) max_examples evenly spaced ones."""
    if max_examples is None or max_examples >= num_windows:
        return list(range(num_windows))
    if not spread:
        return list(range(max_examples))
    return [i * num_windows // max_examples for i in range(max_examples)]


def windows_dataset(args: argparse.Namespace) -> RawTokenDataset:
    """--val_data_dir's non-overlapping windows of --window_size frames at --stride."""
    return RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride, filter_overlaps=True)


def windows_loader(dataset: RawTokenDataset, args: argparse.Namespace) -> Tuple[List[int], DataLoader]:
    """(the indices of the windows evaluated, a loader of them in that order, --batch_size at a time)."""
    indices = example_indices(len(dataset), args.max_examples, args.spread_examples)
    return indices, DataLoader(Subset(dataset, indices), batch_size=args.batch_size, shuffle=False)


def model_windows(model: STMaskGIT, args: argparse.Namespace,
                  withhold_actions: bool = False) -> Tuple[RawTokenDataset, List[int], DataLoader]:
    """`windows_dataset` checked against the model (and its action streams, unless they are withheld), and
    `windows_loader`."""
    dataset = windows_dataset(args)
    check_dataset_matches(model.config, dataset, args.window_size, f"checkpoint {args.checkpoint_dir}",
                          exact_window=False)
    if model.config.uses_actions and not withhold_actions:
        prepare_action_streams(model.config, dataset)
    indices, loader = windows_loader(dataset, args)
    logger.info("evaluating %d windows of %s with %s", len(indices), args.val_data_dir, args.checkpoint_dir)
    return dataset, indices, loader


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


def frame_scorer(args: argparse.Namespace, dataset: RawTokenDataset, device: torch.device,
                 pixel_protocol: Optional[str] = None) -> FrameScorer:
    """The FrameScorer of --tokenizer_ckpt, else the dataset metadata's tokenizer, else DEFAULT_TOKENIZER; with
    LPIPS unless --skip_lpips. pixel_protocol: the protocol that scores futures in pixels (also with --skip_lpips),
    named in the error; None: the teacher-forced protocol, which decodes frames for LPIPS only."""
    tokenizer_ckpt = args.tokenizer_ckpt or dataset.metadata.get("tokenizer_ckpt") or DEFAULT_TOKENIZER
    try:
        return FrameScorer(tokenizer_ckpt, device, with_lpips=not args.skip_lpips)
    except (FileNotFoundError, ValueError) as e:  # missing tokenizer / LPIPS weights, unreadable checkpoint
        if pixel_protocol is not None:
            raise EvaluationError(f"cannot set up decoding{'' if args.skip_lpips else ' + LPIPS'}: {e}\nThe "
                                  f"{pixel_protocol} protocol decodes frames for PSNR and SSIM: pass --tokenizer_ckpt "
                                  f"(and --skip_lpips to go without LPIPS weights).") from None
        raise EvaluationError(f"cannot set up decoding + LPIPS: {e}\nPass --skip_lpips to evaluate without "
                              f"decoding frames.") from None


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _autocast(device: torch.device):
    return torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else contextlib.nullcontext()


def batch_actions(model: STMaskGIT, batch: dict, device: torch.device, args: argparse.Namespace,
                  withhold_actions: bool = False):
    """(real actions (B, T, D) or None, latent ids (B, T) or None) of a loader batch, for the model's inputs; none
    for a model without action inputs or with withhold_actions (every frame gets the learned "no action")."""
    if not model.config.uses_actions or withhold_actions:
        return None, None
    actions_BTD, latent_BT = window_actions(model.config, batch["actions"], where=f"{args.val_data_dir}/actions")
    return (None if actions_BTD is None else actions_BTD.to(device),
            None if latent_BT is None else latent_BT.to(device))


# ------------------------------------------------------------------ teacher-forced protocol
def teacher_forced_evaluate(model: STMaskGIT, loader, args: argparse.Namespace, device: torch.device,
                            scorer: Optional[FrameScorer] = None, outputs: Optional[list] = None,
                            withhold_actions: bool = False) -> dict:
    """Run the teacher-forced protocol over `loader`; return its metrics {TEACHER_FORCED_KEYS..., num_examples}
    (loss: factored CE of the first MaskGIT step's logits; acc, copy_acc: token accuracy of the predictions and of
    copying ground-truth frame t-1; pred_lpips; gen_time, dec_time: s per frame; None where nothing was measured).

    outputs: when a list, per-window frames (frame 0 | predictions | ground truth) are appended to it as numpy.
    """
    metrics = {name: RunningMean() for name in TEACHER_FORCED_KEYS}
    generator = torch.Generator(device=device).manual_seed(args.seed)
    num_examples = 0
    progress = tqdm(loader, desc="evaluate", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        targets_BTHW = x_BTHW[:, 1:]
        actions_BTD, latent_BT = batch_actions(model, batch, device, args, withhold_actions)

        _synchronize(device)
        start = time.perf_counter()
        with _autocast(device):
            samples_BTHW, logits_BVFTHW = teacher_forced(model, x_BTHW, args.maskgit_steps, args.temperature,
                                                         args.unmask_mode, generator=generator,
                                                         actions=actions_BTD, latent_actions=latent_BT)
        _synchronize(device)
        metrics["gen_time"].update(time.perf_counter() - start, B * (T - 1))

        metrics["loss"].update(factored_cross_entropy(logits_BVFTHW, targets_BTHW).sum().item(), targets_BTHW.numel())
        metrics["acc"].update((samples_BTHW == targets_BTHW).sum().item(), targets_BTHW.numel())
        metrics["copy_acc"].update((x_BTHW[:, :-1] == targets_BTHW).sum().item(), targets_BTHW.numel())
        if scorer is not None:
            score_frames(scorer, samples_BTHW.flatten(0, 1), targets_BTHW.flatten(0, 1), metrics, device)
        if outputs is not None:
            outputs.append(torch.cat([x_BTHW[:, :1], samples_BTHW, targets_BTHW], dim=1).cpu().numpy())
        num_examples += B
        progress.set_postfix({name: f"{m.mean:.4g}" for name, m in metrics.items() if m.mean is not None})

    result = {name: metrics[name].mean for name in TEACHER_FORCED_KEYS}
    result["num_examples"] = num_examples
    return result


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


def teacher_forced_run(model: STMaskGIT, loader, dataset: RawTokenDataset, args: argparse.Namespace,
                       device: torch.device, withhold_actions: bool = False) -> Tuple[dict, Optional[FrameScorer]]:
    """`teacher_forced_evaluate` with the scorer the flags ask for (None with --skip_lpips), writing
    --save_outputs_dir; returns (the metrics, the scorer)."""
    scorer = None if args.skip_lpips else frame_scorer(args, dataset, device)
    outputs = [] if args.save_outputs_dir else None
    result = teacher_forced_evaluate(model, loader, args, device, scorer, outputs, withhold_actions)
    if outputs is not None:
        save_outputs(args.save_outputs_dir, outputs, dataset, args.window_size)
    return result, scorer


# ------------------------------------------------------------------ rollout protocol
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
    """Per-window, per-horizon token statistics (N, h) of the generated and the true frames:
    {"rollout_unchanged", "true_unchanged"}: the share of tokens equal to the token at the same position one frame
    earlier (at h = 1: the prompt's last frame); {"rollout_repeated", "true_repeated"}: the share equal to their left
    neighbour in the same frame. Shapes as `score_rollout`."""
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
        raise RuntimeError(f"internal: {len(per_window)} per-window scores for {len(indices)} windows")
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
    """The rollout JSON line from per-horizon score sums {"rollout_psnr": (h,), ...} over windows:
    protocol ("rollout"), num_prompt_frames; per horizon h = 1..T-P (lists, means over windows) rollout_psnr,
    hold_psnr, rollout_ssim, hold_ssim, rollout_lpips, hold_lpips (null without LPIPS), rollout_unchanged,
    true_unchanged, rollout_repeated, true_repeated (`token_statistics`); each with its _mean over horizons;
    rollout_far_psnr, hold_far_psnr (the last horizon's PSNR); gen_time (s per generated frame); num_examples."""
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
                     scorer: FrameScorer, per_window: Optional[list] = None, withhold_actions: bool = False) -> dict:
    """Run the rollout protocol over `loader`; return the JSON line's content (`rollout_result` and the sampler,
    `genie.decoding.decoding_settings`). Action-conditioned models play every action row of the window (the
    sampling challenge gives the future robot states), unless withhold_actions.
    per_window: when a list, each window's own scores are appended to it (`add_rollout_scores`)."""
    P = args.num_prompt_frames
    with_lpips = not args.skip_lpips
    generator = torch.Generator(device=device).manual_seed(args.seed)
    gen_time, sums, num_examples = RunningMean(), {}, 0
    progress = tqdm(loader, desc="rollout", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        actions_BTD, latent_BT = batch_actions(model, batch, device, args, withhold_actions)

        _synchronize(device)
        start = time.perf_counter()
        with _autocast(device):
            tokens_BTHW, _ = generate_frames(model, x_BTHW[:, :P], T - P, **sampler_kwargs(args), generator=generator,
                                      actions=actions_BTD, latent_actions=latent_BT, control=True,
                                      stall_ratio=args.stall_ratio)
        _synchronize(device)
        gen_time.update(time.perf_counter() - start, B * (T - P))

        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window)
        num_examples += B
        progress.set_postfix({"psnr": f"{sums['rollout_psnr'].mean().item() / num_examples:.4g}",
                              "hold": f"{sums['hold_psnr'].mean().item() / num_examples:.4g}"})
    return {**rollout_result(sums, num_examples, P, gen_time.mean), **decoding_settings(args)}


# ------------------------------------------------------------------ latent-action models
@torch.no_grad()
def delta_psnr(model: STMaskGIT, loader, args: argparse.Namespace, device: torch.device,
               scorer: FrameScorer, seeds: List[int]) -> List[float]:
    """Genie's delta-PSNR: mean PSNR of frames generated with the ground truth's latent actions minus that with
    uniformly random latent actions, over the decoded frames after the config's num_prompt_frames. Real action
    inputs, if the model also has them, stay prompt-only in both runs. One value per sampler seed (the random latent
    actions draw from seed + 1), each what that seed alone gives; the windows are read and their true frames decoded
    once for all seeds."""
    P, K = model.config.num_prompt_frames, model.config.num_latent_actions
    if P >= args.window_size:
        raise DataMismatchError(f"delta_psnr: the checkpoint's num_prompt_frames {P} leaves no frame to generate in "
                                f"windows of {args.window_size} frames")
    if args.stall_ratio is not None and P < 2:
        raise DataMismatchError(f"delta_psnr with --stall_ratio: the checkpoint's num_prompt_frames {P} gives no "
                                f"prompt motion to compare with (needs >= 2)")
    kwargs = dict(**sampler_kwargs(args), control=True, stall_ratio=args.stall_ratio)
    # per seed, the same sampling noise in both runs: only the latent actions differ
    generators = [[torch.Generator(device=device).manual_seed(seed) for _ in range(2)] for seed in seeds]
    random_actions = [torch.Generator().manual_seed(seed + 1) for seed in seeds]
    psnrs = [[RunningMean(), RunningMean()] for _ in seeds]
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
                with _autocast(device):
                    tokens_BTHW, _ = generate_frames(model, x_BTHW[:, :P], T - P, generator=generator,
                                              actions=actions_BTD, latent_actions=played_BT, **kwargs)
                frame_psnr = psnr(decode_frames(scorer, tokens_BTHW[:, P:].flatten(0, 1)), truth_NHW3,
                                  value_range=(0.0, 255.0))
                mean.update(frame_psnr.sum().item(), len(frame_psnr))
    return [inferred.mean - random.mean for inferred, random in psnrs]
