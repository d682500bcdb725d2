"""The challenge evaluator's protocols and scores, shared by evaluate.py (the two protocols) and diagnose.py (the same
scores of other futures: withheld actions, per-window lines, the copy ceiling). Functions take an `EvalConfig`; the
flags that fill one are evaluation/cli.py's.

Teacher-forced protocol (`teacher_forced_evaluate`): each window's frames 1..T-1 predicted with MaskGIT from their
ground-truth past, scored by CE, token accuracy, copy_acc (copying ground-truth frame t-1), LPIPS and s/frame.
Rollout protocol (`rollout_evaluate`): each window's first P frames prompt, the rest generated free-running,
decoded and scored per horizon in pixels (PSNR, SSIM, LPIPS) against holding the last prompt frame, plus token
statistics of a freezing or flattening rollout (`rollout_result` lists the keys). `delta_psnr` is Genie's
controllability metric of latent-action models. Nothing here reads lam/ (the latent action probe is evaluate.py's).
"""
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from common.device import apply_cpu_settings, resolve_device
from common.errors import DataMismatchError, InputError, writing
from common.files import atomic_file
from common.images import psnr, ssim
from data import RawTokenDataset, write_token_dataset
from training.action_streams import prepare_action_streams, window_actions
from genie.config import check_dataset_matches
from genie.decoding import DecodingConfig
from genie.inference import changed_share, generate_frames, teacher_forced
from evaluation.metrics import RunningMean, images_to_unit_range
from genie.metrics import factored_cross_entropy
from genie.model import STMaskGIT
from magvit2 import VQModel
from magvit2.lpips import LPIPS
from sample_world.render import raw_frames_path

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


@dataclass
class EvalConfig:
    """What an evaluation scores and how: the windows of val_data_dir (window_size frames at stride, non-overlapping;
    all, the first max_examples, or max_examples spread evenly), batch_size windows at a time, with the model of
    checkpoint_dir; frames decoded by tokenizer_ckpt (default: the dataset metadata's, else DEFAULT_TOKENIZER), LPIPS
    unless skip_lpips; the sampler seeded with `seed`; free-running futures from num_prompt_frames true frames.
    decoding: overrides of the checkpoint's decoding (genie.decoding.DecodingConfig fields; None or missing: the
    checkpoint's). save_outputs_dir: where the teacher-forced protocol writes its predictions (None: nowhere).
    device, num_threads: the process's (common.device)."""
    val_data_dir: str = DEFAULT_VAL_DIR
    checkpoint_dir: str = DEFAULT_CHECKPOINT
    window_size: int = 16
    stride: int = 15
    max_examples: Optional[int] = None
    spread_examples: bool = False
    batch_size: int = 16
    tokenizer_ckpt: Optional[str] = None
    skip_lpips: bool = False
    seed: int = 0
    num_prompt_frames: int = DEFAULT_ROLLOUT_PROMPT_FRAMES
    decoding: Dict[str, Any] = field(default_factory=dict)
    save_outputs_dir: Optional[str] = None
    device: str = "auto"
    num_threads: int = 0


def default_val_data_dir() -> str:
    """data/val_v1.1, or the embedded sample world's validation split when only that exists."""
    if not Path(DEFAULT_VAL_DIR).exists() and Path(SAMPLE_VAL_DIR).exists():
        return SAMPLE_VAL_DIR
    return DEFAULT_VAL_DIR


# ------------------------------------------------------------------ set-up
def start_process(device: str, num_threads: int, seed: int) -> torch.device:
    """The process set-up of a command that scores futures: one process, its device, CPU threads (0: torch's
    default) and seed."""
    check_single_process()
    torch_device = resolve_device(device)
    apply_cpu_settings(num_threads)
    torch.manual_seed(seed)
    return torch_device


def check_single_process() -> None:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1:
        raise EvaluationError(f"evaluation runs in a single process, but WORLD_SIZE={world_size}: launch it with "
                              f"plain `python evaluate.py` (not torchrun / accelerate launch with several processes)")


def load_model(cfg: EvalConfig, device: torch.device, teacher_forced_protocol: bool = False) -> STMaskGIT:
    """cfg.checkpoint_dir on `device` in eval mode, set to decode as cfg.decoding overrides its checkpoint's decoding
    (for the teacher-forced protocol: the overrides of the checkpoint's `DecodingConfig.teacher_forced`)."""
    model = STMaskGIT.from_pretrained(cfg.checkpoint_dir).to(device).eval()
    base = model.decoding.teacher_forced() if teacher_forced_protocol else model.decoding
    apply_decoding(model, cfg.decoding, cfg.checkpoint_dir, base)
    return model


def apply_decoding(model: STMaskGIT, overrides: dict, checkpoint, base: Optional[DecodingConfig] = None) -> None:
    """Set `model` (read from `checkpoint`, named in errors) to decode as `base` (default: its own decoding) with
    the values of `overrides` (DecodingConfig fields) instead, and log what it will use."""
    decoding = (model.decoding if base is None else base).override(**overrides)
    if decoding.copy_bias and model.copy_head is None:
        raise DataMismatchError(f"--copy_bias: the checkpoint {checkpoint} has no copy head (copy_radius)")
    model.set_decoding(decoding)
    logger.info("decoding: %s", ", ".join(f"{k} {v}" for k, v in decoding.to_dict().items()))



def example_indices(num_windows: int, max_examples: Optional[int], spread: bool) -> List[int]:
    """Which windows to evaluate: all, the first max_examples, or (spread) max_examples evenly spaced ones."""
    if max_examples is None or max_examples >= num_windows:
        return list(range(num_windows))
    if not spread:
        return list(range(max_examples))
    return [i * num_windows // max_examples for i in range(max_examples)]


def windows_dataset(cfg: EvalConfig) -> RawTokenDataset:
    """--val_data_dir's non-overlapping windows of --window_size frames at --stride."""
    return RawTokenDataset(cfg.val_data_dir, window_size=cfg.window_size, stride=cfg.stride, filter_overlaps=True)


def windows_loader(dataset: RawTokenDataset, cfg: EvalConfig) -> Tuple[List[int], DataLoader]:
    """(the indices of the windows evaluated, a loader of them in that order, --batch_size at a time)."""
    indices = example_indices(len(dataset), cfg.max_examples, cfg.spread_examples)
    return indices, DataLoader(Subset(dataset, indices), batch_size=cfg.batch_size, shuffle=False)


def model_windows(model: STMaskGIT, cfg: EvalConfig,
                  withhold_actions: bool = False) -> Tuple[RawTokenDataset, List[int], DataLoader]:
    """`windows_dataset` checked against the model (and its action streams, unless they are withheld), and
    `windows_loader`."""
    dataset = windows_dataset(cfg)
    check_dataset_matches(model.config, dataset, cfg.window_size, f"checkpoint {cfg.checkpoint_dir}",
                          exact_window=False)
    if model.config.uses_actions and not withhold_actions:
        prepare_action_streams(model.config, dataset)
    indices, loader = windows_loader(dataset, cfg)
    logger.info("evaluating %d windows of %s with %s", len(indices), cfg.val_data_dir, cfg.checkpoint_dir)
    return dataset, indices, loader


def load_real_frames(raw_npz: Path, num_images: int) -> np.ndarray:
    """The real frames (N, H, W, 3) uint8 of a raw .npz (memory-mapped), checked to be as many as the token
    dataset's `num_images`."""
    with np.load(raw_npz, mmap_mode="r") as npz:
        if "frames" not in npz.files:
            raise DataMismatchError(f"{raw_npz}: no 'frames' array (found {npz.files})")
        frames = npz["frames"]
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) != num_images:
        raise DataMismatchError(f"{raw_npz}: frames {frames.shape} do not match the token dataset's {num_images} "
                                f"images (rebuild the split with build.sh)")
    return frames


@dataclass
class RealFrames:
    """The real frames of evaluated windows: `frames` (N, H, W, 3) uint8 of the whole dataset, and the first frame
    of each window in the loader's order, `stride` frames apart."""
    frames: np.ndarray
    first_frames: List[int]
    stride: int

    def windows(self, start: int, count: int, T: int) -> torch.Tensor:
        """The real frames of windows start..start+count-1 of the loader's order, (count, T, H, W, 3) uint8."""
        inds = np.asarray(self.first_frames[start:start + count])[:, None] + self.stride * np.arange(T)
        return torch.from_numpy(np.ascontiguousarray(self.frames[inds]))


def real_frames_of(dataset: RawTokenDataset, indices: List[int], stride: int) -> Optional[RealFrames]:
    """RealFrames of the windows `indices` when the dataset is a sample world's split with its raw frames beside it,
    else None."""
    raw_npz = raw_frames_path(dataset.data_dir)
    if not raw_npz.is_file():
        return None
    frames = load_real_frames(raw_npz, dataset.metadata["num_images"])
    logger.info("scoring futures against the real frames of %s too", raw_npz)
    return RealFrames(frames, [int(dataset.valid_start_inds[i]) for i in indices], stride)


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


def frame_scorer(cfg: EvalConfig, dataset: RawTokenDataset, device: torch.device,
                 pixel_protocol: Optional[str] = None) -> FrameScorer:
    """The FrameScorer of --tokenizer_ckpt, else the dataset metadata's tokenizer, else DEFAULT_TOKENIZER; with
    LPIPS unless --skip_lpips. pixel_protocol: the protocol that scores futures in pixels (also with --skip_lpips),
    named in the error; None: the teacher-forced protocol, which decodes frames for LPIPS only."""
    tokenizer_ckpt = cfg.tokenizer_ckpt or dataset.metadata.get("tokenizer_ckpt") or DEFAULT_TOKENIZER
    try:
        return FrameScorer(tokenizer_ckpt, device, with_lpips=not cfg.skip_lpips)
    except (FileNotFoundError, ValueError) as e:  # missing tokenizer / LPIPS weights, unreadable checkpoint
        if pixel_protocol is not None:
            raise EvaluationError(f"cannot set up decoding{'' if cfg.skip_lpips else ' + LPIPS'}: {e}\nThe "
                                  f"{pixel_protocol} protocol decodes frames for PSNR and SSIM: pass --tokenizer_ckpt "
                                  f"(and --skip_lpips to go without LPIPS weights).") from None
        raise EvaluationError(f"cannot set up decoding + LPIPS: {e}\nPass --skip_lpips to evaluate without "
                              f"decoding frames.") from None


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _autocast(device: torch.device):
    return torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else contextlib.nullcontext()


def batch_actions(model: STMaskGIT, batch: dict, device: torch.device, cfg: EvalConfig,
                  withhold_actions: bool = False):
    """(real actions (B, T, D) or None, latent ids (B, T) or None) of a loader batch, for the model's inputs; none
    for a model without action inputs or with withhold_actions (every frame gets the learned "no action")."""
    if not model.config.uses_actions or withhold_actions:
        return None, None
    actions_BTD, latent_BT = window_actions(model.config, batch["actions"], where=f"{cfg.val_data_dir}/actions")
    return (None if actions_BTD is None else actions_BTD.to(device),
            None if latent_BT is None else latent_BT.to(device))


# ------------------------------------------------------------------ teacher-forced protocol
def teacher_forced_evaluate(model: STMaskGIT, loader, cfg: EvalConfig, device: torch.device,
                            scorer: Optional[FrameScorer] = None, outputs: Optional[list] = None,
                            withhold_actions: bool = False) -> dict:
    """Run the teacher-forced protocol over `loader`; return its metrics {TEACHER_FORCED_KEYS..., num_examples}
    (loss: factored CE of the first MaskGIT step's logits; acc, copy_acc: token accuracy of the predictions and of
    copying ground-truth frame t-1; pred_lpips; gen_time, dec_time: s per frame; None where nothing was measured).

    outputs: when a list, per-window frames (frame 0 | predictions | ground truth) are appended to it as numpy.
    """
    metrics = {name: RunningMean() for name in TEACHER_FORCED_KEYS}
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    num_examples = 0
    progress = tqdm(loader, desc="evaluate", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        targets_BTHW = x_BTHW[:, 1:]
        actions_BTD, latent_BT = batch_actions(model, batch, device, cfg, withhold_actions)

        _synchronize(device)
        start = time.perf_counter()
        with _autocast(device):
            samples_BTHW, logits_BVFTHW = teacher_forced(model, x_BTHW, **model.decoding.sampler_kwargs(),
                                                         generator=generator,
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


def teacher_forced_run(model: STMaskGIT, loader, dataset: RawTokenDataset, cfg: EvalConfig,
                       device: torch.device, withhold_actions: bool = False) -> Tuple[dict, Optional[FrameScorer]]:
    """`teacher_forced_evaluate` with the scorer the flags ask for (None with --skip_lpips), writing
    --save_outputs_dir; returns (the metrics, the scorer)."""
    scorer = None if cfg.skip_lpips else frame_scorer(cfg, dataset, device)
    outputs = [] if cfg.save_outputs_dir else None
    result = teacher_forced_evaluate(model, loader, cfg, device, scorer, outputs, withhold_actions)
    result["decoding"] = model.decoding.to_dict()
    if outputs is not None:
        save_outputs(cfg.save_outputs_dir, outputs, dataset, cfg.window_size)
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
                  with_lpips: bool, real_NhHW3: Optional[torch.Tensor] = None) -> dict:
    """Per-window, per-horizon scores of generated frames and of the hold baseline, in pixels.

    pred_NhHW: generated token frames (N, h, H, W), h = T - P horizons; last_NHW: the prompt's last token frame
    (N, H, W); future_NhHW: the true token frames the prediction replaces (N, h, H, W).
    Returns {"rollout_psnr", "hold_psnr", "rollout_ssim", "hold_ssim"[, "rollout_lpips", "hold_lpips"]: (N, h)}.
    real_NhHW3: the real frames (N, 1 + h, H, W, 3) uint8 of the prompt's last frame and the h predicted ones, when
    the dataset has them: the same scores against them are added, with the same decoded frames, for the generated
    frames ("rollout_real_*"), the tokenizer's reconstruction of the true frames ("tokenizer_real_*", the ceiling of
    any model speaking its tokens) and holding the last real prompt frame ("hold_real_*").
    """
    N, h = pred_NhHW.shape[:2]
    truth_NhHW3 = decode_frames(scorer, future_NhHW.flatten(0, 1)).unflatten(0, (N, h))
    pred_NhHW3 = decode_frames(scorer, pred_NhHW.flatten(0, 1)).unflatten(0, (N, h))
    hold_NHW3 = decode_frames(scorer, last_NHW)  # decoded once per window, repeated over the horizons
    hold_NhHW3 = hold_NHW3.unsqueeze(1).expand(-1, h, -1, -1, -1)
    scored = [("rollout", pred_NhHW3, truth_NhHW3), ("hold", hold_NhHW3, truth_NhHW3)]
    if real_NhHW3 is not None:
        real = real_NhHW3.to(pred_NhHW3.device)
        scored += [("rollout_real", pred_NhHW3, real[:, 1:]), ("tokenizer_real", truth_NhHW3, real[:, 1:]),
                   ("hold_real", real[:, :1].expand(-1, h, -1, -1, -1), real[:, 1:])]
    scores = {}
    for name, images_NhHW3, against_NhHW3 in scored:
        for metric, values_Nh in image_scores(scorer, images_NhHW3, against_NhHW3, with_lpips).items():
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
                       with_lpips: bool, per_window: Optional[list] = None,
                       real_BTHW3: Optional[torch.Tensor] = None) -> None:
    """Add the per-horizon scores and token statistics of generated windows (B, T, H, W) against the true ones
    (frames P.. generated, frame P - 1 held) to sums {key: (h,) summed over windows}, in place; with a list
    `per_window`, also append each window's own {key: [h floats]}. real_BTHW3: the windows' real frames
    (B, T, H, W, 3), when they are scored against them too (`score_rollout`)."""
    real = None if real_BTHW3 is None else real_BTHW3[:, P - 1:]
    scores = score_rollout(scorer, tokens_BTHW[:, P:], x_BTHW[:, P - 1], x_BTHW[:, P:], with_lpips, real)
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
    true_unchanged, rollout_repeated, true_repeated (`token_statistics`); where the dataset has real frames,
    {rollout,tokenizer,hold}_real_{psnr,ssim,lpips} (`score_rollout`); each with its _mean over horizons;
    rollout_far_psnr, hold_far_psnr (the last horizon's PSNR); gen_time (s per generated frame); num_examples."""
    result = {"protocol": "rollout", "num_prompt_frames": num_prompt_frames}
    keys = [f"{name}_{metric}" for metric in ("psnr", "ssim", "lpips") for name in ("rollout", "hold")]
    keys += [f"{name}_{stat}" for stat in ("unchanged", "repeated") for name in ("rollout", "true")]  # token_statistics
    # against the real frames, only where the dataset has them (a sample world; `score_rollout`)
    keys += [key for key in (f"{name}_real_{metric}" for metric in ("psnr", "ssim", "lpips")
                             for name in ("rollout", "tokenizer", "hold")) if key in sums]
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
def rollout_evaluate(model: STMaskGIT, loader, cfg: EvalConfig, device: torch.device,
                     scorer: FrameScorer, per_window: Optional[list] = None, withhold_actions: bool = False,
                     real: Optional[RealFrames] = None) -> dict:
    """Run the rollout protocol over `loader`; return the JSON line's content (`rollout_result` and the sampler,
    the decoding used). Action-conditioned models play every action row of the window (the
    sampling challenge gives the future robot states), unless withhold_actions.
    per_window: when a list, each window's own scores are appended to it (`add_rollout_scores`). real: the windows'
    real frames (`real_frames_of`), when the futures are also scored against them (`score_rollout`)."""
    P = cfg.num_prompt_frames
    with_lpips = not cfg.skip_lpips
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    gen_time, sums, num_examples = RunningMean(), {}, 0
    progress = tqdm(loader, desc="rollout", unit="batch", file=sys.stderr)
    for batch in progress:
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        actions_BTD, latent_BT = batch_actions(model, batch, device, cfg, withhold_actions)

        _synchronize(device)
        start = time.perf_counter()
        with _autocast(device):
            tokens_BTHW, _ = generate_frames(model, x_BTHW[:, :P], T - P, **model.decoding.sampler_kwargs(),
                                             generator=generator, actions=actions_BTD, latent_actions=latent_BT,
                                             control=True, stall_ratio=model.decoding.stall_ratio)
        _synchronize(device)
        gen_time.update(time.perf_counter() - start, B * (T - P))

        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window,
                           None if real is None else real.windows(num_examples, B, T))
        num_examples += B
        progress.set_postfix({"psnr": f"{sums['rollout_psnr'].mean().item() / num_examples:.4g}",
                              "hold": f"{sums['hold_psnr'].mean().item() / num_examples:.4g}"})
    return {**rollout_result(sums, num_examples, P, gen_time.mean), **model.decoding.to_dict()}


# ------------------------------------------------------------------ latent-action models
@torch.no_grad()
def delta_psnr(model: STMaskGIT, loader, cfg: EvalConfig, device: torch.device,
               scorer: FrameScorer, seeds: List[int]) -> List[float]:
    """Genie's delta-PSNR: mean PSNR of frames generated with the ground truth's latent actions minus that with
    uniformly random latent actions, over the decoded frames after the config's num_prompt_frames. Real action
    inputs, if the model also has them, stay prompt-only in both runs. One value per sampler seed (the random latent
    actions draw from seed + 1), each what that seed alone gives; the windows are read and their true frames decoded
    once for all seeds."""
    P, K = model.config.num_prompt_frames, model.config.num_latent_actions
    if P >= cfg.window_size:
        raise DataMismatchError(f"delta_psnr: the checkpoint's num_prompt_frames {P} leaves no frame to generate in "
                                f"windows of {cfg.window_size} frames")
    if model.decoding.stall_ratio is not None and P < 2:
        raise DataMismatchError(f"delta_psnr with --stall_ratio: the checkpoint's num_prompt_frames {P} gives no "
                                f"prompt motion to compare with (needs >= 2)")
    kwargs = dict(**model.decoding.sampler_kwargs(), control=True, stall_ratio=model.decoding.stall_ratio)
    # per seed, the same sampling noise in both runs: only the latent actions differ
    generators = [[torch.Generator(device=device).manual_seed(seed) for _ in range(2)] for seed in seeds]
    random_actions = [torch.Generator().manual_seed(seed + 1) for seed in seeds]
    psnrs = [[RunningMean(), RunningMean()] for _ in seeds]
    for batch in tqdm(loader, desc="delta_psnr", unit="batch", file=sys.stderr):
        x_BTHW = batch["tokens"].to(device)
        B, T = x_BTHW.shape[:2]
        actions_BTD, latent_BT = batch_actions(model, batch, device, cfg)
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
