"""Train a MAGVIT2 tokenizer (encoder, LFQ, decoder) on video frames or images, with accelerate.

    python -m magvit2.train --train_data data/sample/raw/train.npz --val_data data/sample/raw/val.npz \\
        --output_dir data/sample/tokenizer --resolution 64 --base_channels 64 --ch_mult 1 2 2 --z_channels 18
    python -m magvit2.train ... --resume_from_checkpoint latest      # continue a stopped run

Frames come from .npz files with a `frames` array (N, H, W, 3) uint8 (uncompressed ones are memory-mapped), .npy
arrays of the same shape, folders of such files (searched recursively), folders of images, or glob patterns of any
of these. Frames that are not `resolution` x `resolution` are center-cropped to a square and resized.

Loss (magvit2/losses.py): L1 + LPIPS + LFQ commitment and entropy terms, plus an optional PatchGAN (`--use_gan`).
bf16 autocast on CUDA, fp32 on CPU (see --mixed_precision). The EMA of the weights is what gets evaluated and
exported.

Outputs in --output_dir:
    final_checkpt/          the EMA tokenizer (config.json + model.safetensors): VQModel.from_checkpoint(...)
    checkpoint-<step>/      resumable state, written atomically: the EMA tokenizer (config.json + model.safetensors,
                            loadable as a tokenizer too), raw_model.safetensors, gan.safetensors (discriminator and
                            LeCAM statistics), optimizer and RNG state, trainer_state.json
    log.jsonl               one JSON line per --log_every steps (mean losses) and per evaluation
    eval_results.json       the final held-out PSNR / LPIPS / codebook usage and the training throughput
A run resumed from a checkpoint takes exactly the steps the uninterrupted run would have taken (data order and
augmentation depend only on the seed and the step; RNG states are restored).
"""
import argparse
import glob
import json
import logging
import math
import struct
import sys
import time
import zipfile
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.utils import gather_object, set_seed
from PIL import Image
from safetensors.torch import load_file, save_file
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm.auto import tqdm

from common.cli import (add_device_arg, add_hidden_alias, add_num_threads_arg, apply_cpu_settings, check_optimizer_args,
                        finite_float, non_negative_int, resolve_device, run_main, setup_logging)
from common.errors import InputError, TrainingError, WriteError, writing
from common.files import remove_stale_temp_dirs, write_json_atomic
from common.integrity import verify_manifest
from common.train_state import (TrainingStateError, ResumableBatchSampler, atomic_directory, capture_rng_state,
                               checkpoint_dir, prune_checkpoints, read_json, resolve_resume_path, restore_rng_state,
                               resume_hint, save_state_files, load_state_files)
from magvit2.config import VQConfig
from magvit2.lpips import LPIPS, MIN_SIDE as LPIPS_MIN_SIDE, LPIPSWeightsNotFound
from magvit2.losses import GAN_LOSSES, GAN_WEIGHTINGS, VQLoss
from magvit2.model import VQModel

logger = logging.getLogger("magvit2.train")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
ARRAY_SUFFIXES = (".npz", ".npy")
FRAMES_KEY = "frames"
ARCH_FLAGS = ("base_channels", "ch_mult", "z_channels", "num_res_blocks")
FORMAT_VERSION = 1


class FrameDataError(InputError):
    """A training/validation frame source that cannot be read as uint8 RGB frames."""




# ---------------------------------------------------------------- frames

def _memmap_npz_member(path: Path, member: str) -> Optional[np.ndarray]:
    """Memory-map an uncompressed .npy member of an .npz (np.load would read it whole); None if it is compressed."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member)
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as f:
        f.seek(info.header_offset + 26)  # name and extra-field lengths in the zip local file header
        name_len, extra_len = struct.unpack("<HH", f.read(4))
        f.seek(info.header_offset + 30 + name_len + extra_len)
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran_order, dtype = read_header(f)
        offset = f.tell()
    if dtype.hasobject:
        return None
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order="F" if fortran_order else "C")


def load_frame_array(path: Path) -> np.ndarray:
    """(N, H, W, 3) uint8 frames of an .npz (key `frames`) or .npy file, memory-mapped where possible."""
    try:
        if path.suffix == ".npy":
            frames = np.load(path, mmap_mode="r", allow_pickle=False)
        else:
            with np.load(path, allow_pickle=False) as npz:
                if FRAMES_KEY not in npz.files:
                    raise FrameDataError(f"{path}: no {FRAMES_KEY!r} array (keys: {npz.files}); expected "
                                         f"{FRAMES_KEY} (N, H, W, 3) uint8")
                frames = _memmap_npz_member(path, f"{FRAMES_KEY}.npy")
                if frames is None:
                    frames = npz[FRAMES_KEY]
    except (OSError, ValueError, zipfile.BadZipFile, KeyError) as e:
        if isinstance(e, FrameDataError):
            raise
        raise FrameDataError(f"{path}: cannot read frames ({type(e).__name__}: {e})") from None
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise FrameDataError(f"{path}: frames must be (N, H, W, 3) uint8, got shape {frames.shape} "
                             f"dtype {frames.dtype}")
    if len(frames) == 0:
        raise FrameDataError(f"{path}: contains no frames")
    return frames


def _expand_spec(spec: str) -> List[Path]:
    if any(c in spec for c in "*?["):
        matches = sorted(glob.glob(spec, recursive=True))
        if not matches:
            raise FrameDataError(f"{spec}: the pattern matches no files")
        return [Path(m) for m in matches]
    return [Path(spec)]


def find_frame_sources(specs: List[str]) -> Tuple[List[Path], List[Path]]:
    """Resolve data arguments to (array files, image files), each sorted within its folder."""
    arrays, images = [], []
    for spec in specs:
        for path in _expand_spec(spec):
            if path.is_dir():
                found = sorted(p for p in path.rglob("*") if p.suffix.lower() in ARRAY_SUFFIXES and p.is_file())
                pics = sorted(p for p in path.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
                if not found and not pics:
                    raise FrameDataError(f"{path}: no .npz/.npy frame files or images "
                                         f"({', '.join(IMAGE_SUFFIXES)}) in this folder")
                arrays += found
                images += pics
            elif path.is_file():
                if path.suffix.lower() in ARRAY_SUFFIXES:
                    arrays.append(path)
                elif path.suffix.lower() in IMAGE_SUFFIXES:
                    images.append(path)
                else:
                    raise FrameDataError(f"{path}: unsupported file type (expected .npz, .npy or an image)")
            else:
                raise FrameDataError(f"{path}: no such file or folder")
    return arrays, images


def to_square(frame_HWC: np.ndarray, resolution: int) -> np.ndarray:
    """Center-crop to a square and resize to resolution x resolution (bicubic); a no-op for frames that fit."""
    h, w = frame_HWC.shape[:2]
    if h == w == resolution:
        return frame_HWC
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    image = Image.fromarray(np.ascontiguousarray(frame_HWC[top:top + side, left:left + side]))
    return np.asarray(image.resize((resolution, resolution), Image.Resampling.BICUBIC))


class FrameDataset(Dataset):
    """Frames from array files and images as uint8 tensors (3, resolution, resolution)."""

    def __init__(self, specs: List[str], resolution: int):
        array_paths, self.image_paths = find_frame_sources(specs)
        self.arrays = [load_frame_array(p) for p in array_paths]
        self.offsets = np.cumsum([0] + [len(a) for a in self.arrays])
        self.resolution = resolution
        self.description = ", ".join(specs)

    def __len__(self) -> int:
        return int(self.offsets[-1]) + len(self.image_paths)

    def _image(self, path: Path) -> np.ndarray:
        try:
            with Image.open(path) as image:
                return np.asarray(image.convert("RGB"))
        except OSError as e:
            raise FrameDataError(f"{path}: cannot read image ({e})") from None

    def __getitem__(self, index: int) -> torch.Tensor:
        if index < self.offsets[-1]:
            k = int(np.searchsorted(self.offsets, index, side="right")) - 1
            frame_HWC = np.asarray(self.arrays[k][index - self.offsets[k]])
        else:
            frame_HWC = self._image(self.image_paths[index - int(self.offsets[-1])])
        return torch.from_numpy(to_square(frame_HWC, self.resolution).transpose(2, 0, 1).copy())


def build_datasets(args, resolution: int) -> Tuple[Dataset, Optional[Dataset]]:
    """(train, val); without --val_data the last --val_fraction of the training frames are held out."""
    train = FrameDataset(args.train_data, resolution)
    if args.val_data:
        return train, FrameDataset(args.val_data, resolution)
    num_val = int(round(len(train) * args.val_fraction)) if len(train) > 1 else 0
    if args.val_fraction > 0:
        num_val = max(1, num_val)
    if num_val == 0:
        return train, None
    return Subset(train, range(len(train) - num_val)), Subset(train, range(len(train) - num_val, len(train)))


def to_model_input(frames_B3HW: torch.Tensor, device: torch.device, channels_last: bool) -> torch.Tensor:
    """uint8 frames -> float images in [-1, 1] on `device`."""
    x_B3HW = frames_B3HW.to(device, non_blocking=True).float() / 127.5 - 1.0
    return x_B3HW.contiguous(memory_format=torch.channels_last) if channels_last else x_B3HW


def random_hflip(x_B3HW: torch.Tensor, seed: int, step: int) -> torch.Tensor:
    """Flip each image left-right with probability 1/2; the coin flips depend only on (seed, step)."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + step)
    flip_B = (torch.rand(x_B3HW.shape[0], generator=generator) < 0.5).to(x_B3HW.device).view(-1, 1, 1, 1)
    return torch.where(flip_B, x_B3HW.flip(-1), x_B3HW)


# ---------------------------------------------------------------- model state

class EMA:
    """Exponential moving average of a model's weights, with the usual warm-up min(decay, (1 + n) / (10 + n))."""

    def __init__(self, model: VQModel, decay: float):
        self.decay = decay
        self.model = VQModel(model.config).to(next(model.parameters()).device)
        self.model.load_state_dict(model.state_dict())
        self.model.eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int) -> None:
        decay = min(self.decay, (1 + step) / (10 + step))
        for ema_p, p in zip(self.model.parameters(), model.parameters()):
            ema_p.lerp_(p.detach().float(), 1.0 - decay)


def codebook_usage(token_ids: torch.Tensor, codebook_size: int) -> Dict[str, float]:
    """Distinct codes used, their fraction of the codebook, and the perplexity exp(H) of the code histogram."""
    _, counts = torch.unique(token_ids.flatten(), return_counts=True)
    probs = counts.double() / counts.sum()
    entropy = float(-(probs * probs.log()).sum())
    return {"codes_used": int(len(counts)), "codebook_usage": len(counts) / codebook_size,
            "perplexity": math.exp(entropy)}


@torch.no_grad()
def evaluate(model: VQModel, dataset: Dataset, perceptual: Optional[LPIPS], args, device: torch.device,
             autocast) -> Dict[str, float]:
    """Held-out reconstruction quality of `model` on up to --max_eval_frames evenly spaced frames."""
    count = min(len(dataset), args.max_eval_frames)
    indices = np.linspace(0, len(dataset) - 1, count).round().astype(int).tolist()
    loader = DataLoader(Subset(dataset, indices), batch_size=args.batch_size, shuffle=False)
    was_training = model.training
    model.eval()
    psnr, lpips, ids = [], [], []
    for frames in loader:
        x_B3HW = to_model_input(frames, device, args.channels_last)
        with autocast():
            x_rec_B3HW, quant = model(x_B3HW)
        x_rec_B3HW = x_rec_B3HW.float().clamp(-1, 1)
        mse_B = ((x_rec_B3HW - x_B3HW) / 2).pow(2).mean(dim=(1, 2, 3))  # on the [0, 1] scale
        psnr.append(10 * torch.log10(1.0 / mse_B.clamp_min(1e-10)))
        if perceptual is not None:
            lpips.append(perceptual(x_rec_B3HW, x_B3HW))
        ids.append(quant.token_ids.cpu())
    model.train(was_training)
    metrics = {"val_psnr": float(torch.cat(psnr).mean()), "val_frames": count}
    if lpips:
        metrics["val_lpips"] = float(torch.cat(lpips).mean())
    metrics.update({f"val_{k}": v for k, v in codebook_usage(torch.cat(ids), model.config.codebook_size).items()})
    return metrics


# ---------------------------------------------------------------- checkpoints

def save_checkpoint(ckpt_dir: Path, step: int, model: VQModel, ema: EMA, loss_fn: VQLoss, opt_g, opt_d,
                    rng_states: list, args) -> None:
    """Write a resumable training checkpoint atomically (a temp directory renamed into place)."""
    with atomic_directory(ckpt_dir, "the tokenizer training checkpoint") as tmp:
        ema.model.save_pretrained(tmp)  # the directory doubles as a tokenizer checkpoint (EMA weights)
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
                  str(tmp / "raw_model.safetensors"))
        if loss_fn.discriminator is not None:
            gan_state = {f"discriminator.{k}": v for k, v in loss_fn.discriminator.state_dict().items()}
            gan_state.update({f"lecam.{k}": v for k, v in loss_fn.lecam.state_dict().items()})
            save_file({k: v.detach().cpu().contiguous() for k, v in gan_state.items()}, str(tmp / "gan.safetensors"))
        save_state_files(tmp, "optimizer", {"generator": opt_g.state_dict(),
                                            "discriminator": opt_d.state_dict() if opt_d is not None else None})
        save_state_files(tmp, "rng", rng_states)
        trainer_state = {"format_version": FORMAT_VERSION, "step": step, "config": model.config.to_dict(),
                         "args": vars(args)}
        (tmp / "trainer_state.json").write_text(json.dumps(trainer_state, indent=2, sort_keys=True) + "\n")


def _read_weights(path: Path) -> Dict[str, torch.Tensor]:
    if not path.is_file():
        raise TrainingStateError(f"{path.parent}: missing {path.name}")
    try:
        return load_file(str(path))
    except Exception as e:  # noqa: BLE001 - safetensors raises several error types for corrupt files
        raise TrainingStateError(f"{path}: unreadable safetensors file ({e})") from None


def load_checkpoint(ckpt_dir: Path, model: VQModel, ema: EMA, loss_fn: VQLoss, opt_g, opt_d,
                    config: VQConfig) -> Tuple[int, list]:
    """Restore a checkpoint written by `save_checkpoint`; returns (step, per-process RNG states)."""
    verify_manifest(ckpt_dir)  # IntegrityError naming a file whose bytes changed since it was written
    trainer = read_json(ckpt_dir / "trainer_state.json", "trainer state")
    if trainer.get("format_version") != FORMAT_VERSION:
        raise TrainingStateError(f"{ckpt_dir / 'trainer_state.json'}: format_version "
                                 f"{trainer.get('format_version')!r}, this code reads {FORMAT_VERSION}")
    if trainer.get("config") != config.to_dict():
        changed = sorted(k for k, v in config.to_dict().items() if trainer.get("config", {}).get(k) != v)
        raise TrainingStateError(f"{ckpt_dir}: was trained with a different tokenizer config (fields {changed} "
                                 f"differ); resume with the same --vq_config / architecture flags")
    model.load_state_dict(_read_weights(ckpt_dir / "raw_model.safetensors"))
    ema.model.load_state_dict(_read_weights(ckpt_dir / "model.safetensors"))
    optim = load_state_files(ckpt_dir, "optimizer")
    opt_g.load_state_dict(optim["generator"])
    gan_path = ckpt_dir / "gan.safetensors"
    if loss_fn.discriminator is not None:
        if gan_path.is_file() and optim["discriminator"] is not None:
            gan_state = _read_weights(gan_path)
            for prefix, module in (("discriminator.", loss_fn.discriminator), ("lecam.", loss_fn.lecam)):
                module.load_state_dict({k[len(prefix):]: v for k, v in gan_state.items() if k.startswith(prefix)})
            opt_d.load_state_dict(optim["discriminator"])
        else:
            logger.warning("%s was trained without the GAN; the discriminator starts from scratch", ckpt_dir)
    return int(trainer["step"]), load_state_files(ckpt_dir, "rng")


# ---------------------------------------------------------------- training

def build_config(args) -> VQConfig:
    """VQConfig from --vq_config (default: the 1X architecture), overridden by the architecture flags given."""
    source = args.vq_config or "VQConfig defaults"
    fields = VQConfig.from_pretrained(args.vq_config).to_dict() if args.vq_config else VQConfig().to_dict()
    for name in ARCH_FLAGS + ("resolution", "disc_start"):
        if getattr(args, name) is not None:
            fields[name] = getattr(args, name)
    fields["codebook_size"] = 2 ** fields["z_channels"]
    return VQConfig.from_dict(fields, source=f"{source} + command-line flags")


def make_accelerator(args) -> Accelerator:
    use_cpu = resolve_device(args.device).type == "cpu"
    mixed_precision = args.mixed_precision if args.mixed_precision != "auto" else ("no" if use_cpu else "bf16")
    return Accelerator(cpu=use_cpu, mixed_precision=mixed_precision,
                       log_with=None if args.report_to == "none" else args.report_to, project_dir=args.output_dir)


def load_perceptual(args) -> Optional[LPIPS]:
    if args.no_lpips:
        return None
    try:
        return LPIPS(args.lpips_weights)
    except LPIPSWeightsNotFound as e:
        raise LPIPSWeightsNotFound(f"{e}\n(magvit2.train: pass --no_lpips to train with L1 only)") from None


class RunLog:
    """Running means of the step logs, flushed to log.jsonl (and the trackers) every --log_every steps."""

    def __init__(self, path: Path, accelerator: Accelerator, enabled: bool):
        self.path, self.accelerator, self.enabled = path, accelerator, enabled
        self.sums: Dict[str, float] = {}
        self.counts: Dict[str, int] = {}

    def add(self, logs: Dict[str, float]) -> None:
        for k, v in logs.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
            self.counts[k] = self.counts.get(k, 0) + 1

    def flush(self, step: int) -> None:
        means = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums, self.counts = {}, {}
        if means:
            self.write(step, means)

    def write(self, step: int, metrics: Dict[str, float]) -> None:
        self.accelerator.log(metrics, step=step)
        if self.enabled:
            with writing("the training log", self.path), open(self.path, "a") as f:
                f.write(json.dumps({"step": step, **metrics}) + "\n")


class Trainer:
    """Owns the accelerator, the tokenizer, its EMA, the losses and optimizers of one training run."""

    def __init__(self, args):
        self.args = args
        self.output_dir = Path(args.output_dir)
        self.accelerator = make_accelerator(args)
        self.is_main = self.accelerator.is_main_process
        if self.is_main:
            self.output_dir.mkdir(parents=True, exist_ok=True)
            remove_stale_temp_dirs(self.output_dir)
        set_seed(args.seed)
        self.config = build_config(args)
        self.train_ds, self.val_ds = build_datasets(args, self.config.resolution)
        self.sampler, self.loader = self._build_loader()
        self.perceptual = load_perceptual(args)
        if self.perceptual is not None and self.config.resolution < LPIPS_MIN_SIDE:
            raise TrainingError(f"LPIPS (AlexNet) needs images of at least {LPIPS_MIN_SIDE}px, the resolution is "
                                f"{self.config.resolution}; train with --no_lpips")
        self.loss_fn = VQLoss(self.config, self.perceptual, use_gan=args.use_gan, gan_loss=args.gan_loss,
                              gan_weighting=args.gan_weighting, disc_layers=args.disc_layers,
                              perceptual_every=args.perceptual_every)
        if args.use_gan and self.config.resolution < self.loss_fn.discriminator.min_input_size:
            raise TrainingError(f"--disc_layers {args.disc_layers} needs images of at least "
                                f"{self.loss_fn.discriminator.min_input_size}px, the resolution is "
                                f"{self.config.resolution}; lower --disc_layers")
        self._build_model_and_optimizers()
        self.ema = EMA(self.raw_model, args.ema_decay)
        self.run_log = RunLog(self.output_dir / "log.jsonl", self.accelerator, self.is_main)
        self.evaluated: Dict[int, Dict[str, float]] = {}

    def _build_loader(self) -> Tuple[ResumableBatchSampler, DataLoader]:
        args, acc = self.args, self.accelerator
        sampler = ResumableBatchSampler(len(self.train_ds), args.batch_size, num_replicas=acc.num_processes,
                                        rank=acc.process_index, seed=args.seed)
        if sampler.batches_per_epoch == 0:
            raise TrainingError(f"{len(self.train_ds)} training frames are fewer than one batch of {args.batch_size} "
                                f"per process ({acc.num_processes} processes); lower --batch_size")
        num_workers = args.num_workers if args.num_workers is not None else (0 if acc.device.type == "cpu" else 4)
        # Its own generator: a DataLoader iterator draws a seed from the global RNG, and a resumed run starts its
        # epoch iterator at a different step than the uninterrupted one would.
        loader = DataLoader(self.train_ds, batch_sampler=sampler, num_workers=num_workers,
                            pin_memory=acc.device.type == "cuda", persistent_workers=num_workers > 0,
                            generator=torch.Generator().manual_seed(args.seed))
        return sampler, loader

    def _build_model_and_optimizers(self) -> None:
        args, acc = self.args, self.accelerator
        model = VQModel(self.config)
        if args.channels_last:
            model = model.to(memory_format=torch.channels_last)
        adam = dict(betas=(args.adam_beta_1, args.adam_beta_2), weight_decay=args.weight_decay,
                    fused=acc.device.type == "cuda" or None)
        self.model, self.opt_g = acc.prepare(model, torch.optim.AdamW(model.parameters(), lr=args.learning_rate,
                                                                      **adam))
        self.raw_model = acc.unwrap_model(self.model)
        self.disc = self.opt_d = None
        if args.use_gan:  # `disc` may be a DDP wrapper; loss_fn keeps the plain module for the generator's pass
            opt_d = torch.optim.AdamW(self.loss_fn.discriminator.parameters(),
                                      lr=args.disc_learning_rate or args.learning_rate, **adam)
            self.disc, self.opt_d = acc.prepare(self.loss_fn.discriminator, opt_d)
        self.loss_fn.to(acc.device)

    def resume(self) -> int:
        """Restore --resume_from_checkpoint if given (and present); returns the step to continue from."""
        resume_dir = resolve_resume_path(self.output_dir, self.args.resume_from_checkpoint)
        if resume_dir is None:
            if self.args.resume_from_checkpoint:
                logger.info("no checkpoint in %s yet; starting from scratch", self.output_dir)
            return 0
        step, rng_states = load_checkpoint(resume_dir, self.raw_model, self.ema, self.loss_fn, self.opt_g,
                                           self.opt_d, self.config)
        rank, world = self.accelerator.process_index, self.accelerator.num_processes
        restore_rng_state(rng_states[rank] if len(rng_states) == world else rng_states[0])
        logger.info("resumed from %s at step %d", resume_dir, step)
        return step

    def train_step(self, batch: torch.Tensor, step: int) -> Dict[str, float]:
        """One generator update (and one discriminator update once the GAN is active) on uint8 frames."""
        args, acc, loss_fn = self.args, self.accelerator, self.loss_fn
        x_B3HW = to_model_input(batch, acc.device, args.channels_last)
        if args.augment:
            x_B3HW = random_hflip(x_B3HW, args.seed * acc.num_processes + acc.process_index, step)
        with acc.autocast():
            x_rec_B3HW, quant = self.model(x_B3HW)
            loss, logs = loss_fn.generator_loss(x_B3HW, x_rec_B3HW, quant, step,
                                                last_layer=self.raw_model.decoder.conv_out.weight)
        if not torch.isfinite(loss):
            raise TrainingError(f"the loss became {float(loss)} at step {step}; lower --learning_rate")
        self._update(loss, self.model, self.opt_g)
        if loss_fn.gan_active(step):
            with acc.autocast():
                d_loss, d_logs = loss_fn.discriminator_loss(x_B3HW, x_rec_B3HW, step, discriminator=self.disc)
            self._update(d_loss, self.disc, self.opt_d)
            logs.update(d_logs)
        self.ema.update(self.raw_model, step)
        return {k: float(v) for k, v in logs.items()}

    def _update(self, loss: torch.Tensor, module: torch.nn.Module, optimizer) -> None:
        self.accelerator.backward(loss)
        if self.args.max_grad_norm > 0:
            self.accelerator.clip_grad_norm_(module.parameters(), self.args.max_grad_norm)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    def evaluate(self, step: int) -> Dict[str, float]:
        """Held-out metrics of the EMA model (once per step), logged."""
        if step not in self.evaluated:
            metrics = evaluate(self.ema.model, self.val_ds, self.perceptual, self.args, self.accelerator.device,
                               self.accelerator.autocast)
            self.run_log.write(step, metrics)
            logger.info("step %d: %s", step, ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()))
            self.evaluated[step] = metrics
        return self.evaluated[step]

    def checkpoint(self, step: int) -> None:
        acc = self.accelerator
        rng_states = gather_object([capture_rng_state()]) if acc.num_processes > 1 else [capture_rng_state()]
        if self.is_main:
            save_checkpoint(checkpoint_dir(self.output_dir, step), step, self.raw_model, self.ema, self.loss_fn,
                            self.opt_g, self.opt_d, rng_states, self.args)
            prune_checkpoints(self.output_dir, self.args.checkpoints_total_limit)
        acc.wait_for_everyone()

    def after_step(self, step: int) -> None:
        args = self.args
        if step % args.log_every == 0:
            self.run_log.flush(step)
        if self.val_ds is not None and args.eval_every_n_steps > 0 and step % args.eval_every_n_steps == 0 \
                and self.is_main:
            self.evaluate(step)
        if args.checkpointing_steps > 0 and step % args.checkpointing_steps == 0:
            self.checkpoint(step)

    def fit(self) -> Dict[str, float]:
        """Train to --max_train_steps; export the EMA tokenizer; returns the final metrics."""
        args = self.args
        step = start_step = self.resume()
        if self.is_main:
            logger.info("tokenizer %.2fM parameters, %d training frames, %s validation frames, device %s",
                        sum(p.numel() for p in self.raw_model.parameters()) / 1e6, len(self.train_ds),
                        len(self.val_ds) if self.val_ds is not None else "no", self.accelerator.device)
        self.accelerator.init_trackers("magvit2_tokenizer", config={k: v for k, v in vars(args).items()
                                                                    if isinstance(v, (int, float, str, bool))})
        losses = []
        start_time = time.perf_counter()
        progress = tqdm(total=args.max_train_steps, initial=step, disable=not self.is_main, desc="tokenizer")
        self.model.train()
        while step < args.max_train_steps:
            epoch, start_batch = divmod(step, self.sampler.batches_per_epoch)
            self.sampler.set_epoch(epoch, start_batch)
            for batch in self.loader:
                logs = self.train_step(batch, step)
                step += 1
                losses.append(logs["loss"])
                self.run_log.add(logs)
                progress.update(1)
                progress.set_postfix({k: f"{logs[k]:.3g}" for k in ("loss", "l1", "lpips", "g_loss", "d_loss")
                                      if k in logs})
                self.after_step(step)
                if step >= args.max_train_steps:
                    break
        progress.close()
        self.run_log.flush(step)
        return self.finish(step, step - start_step, time.perf_counter() - start_time, losses)

    def finish(self, step: int, steps_done: int, elapsed: float, losses: List[float]) -> Dict[str, float]:
        args = self.args
        if args.checkpointing_steps > 0 and step % args.checkpointing_steps != 0:
            self.checkpoint(step)  # so that a longer run can always continue from the end of this one
        frames = steps_done * args.batch_size * self.accelerator.num_processes
        results = {"step": step, "train_steps_per_second": steps_done / elapsed if steps_done else 0.0,
                   "train_frames_per_second": frames / elapsed if steps_done else 0.0}
        if losses:
            results.update(first_loss=losses[0], final_loss=losses[-1])
        if self.is_main:
            with writing("the final tokenizer", self.output_dir / "final_checkpt"):
                self.ema.model.save_pretrained(self.output_dir / "final_checkpt")
            if self.val_ds is not None:
                results.update(self.evaluate(step))
            write_json_atomic(self.output_dir / "eval_results.json", {k: results[k] for k in sorted(results)},
                              "the evaluation results")
            logger.info("%d steps in %.1fs (%.3g steps/s); EMA tokenizer written to %s", steps_done, elapsed,
                        results["train_steps_per_second"], self.output_dir / "final_checkpt")
        self.accelerator.end_training()
        return results


def run(args) -> Dict[str, float]:
    """Train as configured by `args` (see parse_args); returns the final metrics (also in eval_results.json)."""
    apply_cpu_settings(args.num_threads)
    return Trainer(args).fit()


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_argument_group("data")
    g.add_argument("--train_data", nargs="+", required=True,
                   help="Training frames: .npz files (key 'frames', (N, H, W, 3) uint8), .npy arrays, folders of "
                        "them or of images, or glob patterns (quote them).")
    g.add_argument("--val_data", nargs="+", default=None,
                   help="Held-out frames in the same forms (default: the last --val_fraction of --train_data).")
    g.add_argument("--val_fraction", type=finite_float, default=0.05,
                   help="Fraction of the training frames held out when --val_data is not given (0: none).")
    g.add_argument("--max_eval_frames", type=int, default=256,
                   help="Evenly spaced held-out frames used by each evaluation.")
    g.add_argument("--augment", action="store_true", help="Random horizontal flips of the training frames.")
    g.add_argument("--num_workers", type=non_negative_int, default=None,
                   help="DataLoader worker processes (default: 0 on CPU, 4 on CUDA).")

    g = p.add_argument_group("model (flags override --vq_config; without either the 1X architecture is used)")
    g.add_argument("--vq_config", default=None, help="VQConfig JSON file (architecture and loss weights).")
    g.add_argument("--resolution", type=int, default=None, help="Training image side (frames are resized to it).")
    g.add_argument("--base_channels", type=int, default=None, help="Width of the first level.")
    g.add_argument("--ch_mult", type=int, nargs="+", default=None,
                   help="Width multiplier per level; len(ch_mult) - 1 stride-2 downsamplings (e.g. 1 2 2: 64 -> 16).")
    g.add_argument("--z_channels", type=int, default=None, help="Latent channels = bits per token (codebook 2^z).")
    g.add_argument("--num_res_blocks", type=int, default=None, help="Residual blocks per level.")

    g = p.add_argument_group("loss")
    g.add_argument("--lpips_weights", default=None,
                   help="Converted LPIPS .safetensors (default: $GENIE_LPIPS_WEIGHTS, the user cache, the torch hub).")
    g.add_argument("--no_lpips", action="store_true",
                   help="No perceptual loss or LPIPS metric (for machines without LPIPS weights).")
    g.add_argument("--perceptual_every", type=int, default=1,
                   help="Compute the LPIPS loss on every N-th step only (a CPU speed knob).")
    gan = g.add_mutually_exclusive_group()
    gan.add_argument("--use_gan", dest="use_gan", action="store_true",
                     help="Add the PatchGAN adversarial loss from step disc_start on.")
    gan.add_argument("--no_gan", dest="use_gan", action="store_false", help="No adversarial loss (the default).")
    p.set_defaults(use_gan=False)
    g.add_argument("--gan_loss", default="hinge", choices=GAN_LOSSES, help="GAN objective.")
    g.add_argument("--gan_weighting", default="adaptive", choices=GAN_WEIGHTINGS,
                   help="Generator GAN weight: adaptive (grad-norm ratio at the decoder's last layer x disc_weight) "
                        "or fixed (gen_loss_weight, as the published Open-MAGVIT2 configs).")
    g.add_argument("--disc_layers", type=int, default=3,
                   help="Stride-2 layers of the patch discriminator (3: 70x70 patches; images >= 3 * 2^layers px).")
    g.add_argument("--disc_start", type=int, default=None, help="Step at which the GAN starts (overrides the config).")

    g = p.add_argument_group("optimization")
    g.add_argument("--batch_size", type=int, default=16, help="Frames per process per step.")
    g.add_argument("--learning_rate", type=finite_float, default=1e-4, help="Tokenizer AdamW learning rate.")
    g.add_argument("--disc_learning_rate", type=finite_float, default=None,
                   help="Discriminator AdamW learning rate (default: --learning_rate).")
    g.add_argument("--adam_beta_1", type=finite_float, default=0.5,
                   help="AdamW beta1 (0.5 as in GAN tokenizer training).")
    g.add_argument("--adam_beta_2", type=finite_float, default=0.9, help="AdamW beta2.")
    add_hidden_alias(g, "--adam_beta1", "adam_beta_1", type=finite_float)  # the spelling before train.py's was adopted
    add_hidden_alias(g, "--adam_beta2", "adam_beta_2", type=finite_float)
    g.add_argument("--weight_decay", type=finite_float, default=0.0, help="AdamW weight decay.")
    g.add_argument("--max_grad_norm", type=finite_float, default=1.0, help="Gradient clipping norm (<= 0: none).")
    g.add_argument("--max_train_steps", type=int, default=1000, help="Total optimizer steps.")
    g.add_argument("--ema_decay", type=finite_float, default=0.999, help="Decay of the EMA weights that get exported.")
    g.add_argument("--seed", type=int, default=0, help="Seed of initialization, data order and augmentation.")
    add_device_arg(g, choices=("auto", "cpu", "cuda"), help="auto: CUDA when available, else CPU.")
    add_num_threads_arg(g)
    g.add_argument("--mixed_precision", default="auto", choices=("auto", "no", "bf16"),
                   help="auto: bf16 autocast on CUDA, fp32 on CPU. bf16 on a CPU with AVX512-BF16/AMX is ~1.6x faster.")
    g.add_argument("--channels_last", action="store_true",
                   help="channels_last memory format for the convolutions (~1.25x faster fp32 training on CPU).")

    g = p.add_argument_group("evaluation, checkpoints and logging")
    g.add_argument("--output_dir", required=True, help="Where checkpoints, final_checkpt and logs go.")
    g.add_argument("--eval_every_n_steps", type=non_negative_int, default=500,
                   help="Held-out PSNR / LPIPS / codebook usage every N steps (0: only at the end).")
    g.add_argument("--checkpointing_steps", type=non_negative_int, default=500,
                   help="Save a resumable checkpoint every N steps and at the end (0: never).")
    g.add_argument("--checkpoints_total_limit", type=non_negative_int, default=2,
                   help="Keep the newest N checkpoints (0: all).")
    g.add_argument("--resume_from_checkpoint", default=None,
                   help="'latest' (newest checkpoint in --output_dir, if any) or a checkpoint directory.")
    g.add_argument("--log_every", type=int, default=10, help="Steps between lines of log.jsonl / tracker logs.")
    g.add_argument("--report_to", default="none", choices=("none", "tensorboard", "wandb"),
                   help="Also send metrics to this tracker.")
    args = p.parse_args(argv)
    for name in ("batch_size", "max_eval_frames", "perceptual_every", "log_every", "disc_layers"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.max_train_steps < 0:
        p.error(f"--max_train_steps must be >= 0, got {args.max_train_steps}")
    if not 0.0 <= args.val_fraction < 1.0:
        p.error(f"--val_fraction must be in [0, 1), got {args.val_fraction}")
    check_optimizer_args(p, args, rates=("learning_rate", "disc_learning_rate"),
                         betas=("adam_beta_1", "adam_beta_2", "ema_decay"))
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    setup_logging()
    try:
        run(args)
    except WriteError as e:  # full disk / I/O error: say what failed and where the run can resume from
        raise WriteError(f"{e}; {resume_hint(args.output_dir)}", e.errno) from e


if __name__ == "__main__":
    sys.exit(run_main("magvit2.train", main))
