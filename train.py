#!/usr/bin/env python
"""Train the GENIE dynamics model (STMaskGIT) on a token dataset, with accelerate (CPU, one GPU, many GPUs/nodes).

    python train.py --genie_config genie/configs/sample_world.json --output_dir data/genie_model
    python train.py ... --resume_from_checkpoint latest       # continue a killed/preempted run
    python train.py ... --use_actions buttons,driving_command  # condition on real actions (actions/<name>.bin)
    python train.py ... --use_actions buttons,driving_command --action_step_mean  # ... averaged over each window step
    python train.py ... --use_latent_actions 8                 # condition on LAM latent actions (latent_action.bin)
    python train.py ... --ema_decay 0.995                      # final_checkpt: a moving average of the weights
    accelerate launch --multi_gpu --num_processes 2 train.py ...   # DDP: NCCL on GPUs, gloo on a CPU-only machine
    torchrun --nproc_per_node 2 train.py ...                       # the same without accelerate's launcher

(`accelerate launch --cpu --num_processes N` starts a single process unless MPI is configured.)

The model owns its loss (model(batch, recipe).loss, genie/model.py); this script owns the loop.

Crash safety: every `--checkpointing_steps` optimizer steps the full training state is written atomically to
`output_dir/checkpoint-<step>/` (see common/train_state.py); older ones are pruned only after it is complete, and a
full disk ends the run with one line naming the last complete checkpoint. The data order depends only on the seed and
the epoch, and the collator's masking only on the seed and the position in the data, so a run resumed from a
checkpoint takes exactly the steps the uninterrupted run would have taken. SIGTERM saves a checkpoint and exits cleanly.
A step whose loss or gradient is NaN/inf is skipped; `--max_nonfinite_steps` of them in a row stop the run after
saving a checkpoint of the last good weights (the data position is past the bad batches). A run whose loss stays
above twice a uniform guess's for `--max_diverged_steps` steps in a row has diverged and stops with an error, its
weights left unsaved: minutes instead of hours lost to a learning rate too high for the model.
"""
import argparse
import contextlib
import dataclasses
import importlib.util
import logging
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.utils import gather_object, set_seed
from safetensors.torch import load_model
from torch.utils.data import DataLoader, Subset
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

import genie.configs
from common.cli import (NO_NATIVE_BF16, add_num_threads_arg, apply_cpu_settings, check_optimizer_args,
                        cpu_has_native_bf16, finite_float, setup_logging)
from common.ema import WeightAverage
from common.errors import InputError, TrainingError, WriteError
from common.schedules import LR_SCHEDULES, lr_multiplier
from data import RawTokenDataset
from training.action_streams import action_statistics, latent_action_sidecar, prepare_action_streams, stream_dims
from genie.checkpoint import load_state_dict_checked
from genie.config import ConfigError, GenieConfig, TrainingRecipe, check_dataset_matches
from training.masking import get_maskgit_collator
from genie.model import MaskGITBatch
from genie.model import STMaskGIT
from common.files import remove_stale_temp_dirs
from common import muon
from common.train_state import (EMA_DIR, TrainingStateError, ResumableBatchSampler, atomic_directory,
                               capture_rng_state, checkpoint_dir, list_checkpoints, load_training_checkpoint,
                               prune_checkpoints, resolve_resume_path, restore_rng_state, resume_hint,
                               save_training_checkpoint)

logger = logging.getLogger("train")

CONFIG_DIR = Path(genie.configs.__file__).parent


def first_existing(*paths) -> str:
    """The first path that exists, else the last one (so the error message names the canonical location)."""
    for p in paths:
        if Path(p).exists():
            return str(p)
    return str(paths[-1])


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="Train a spatio-temporal MaskGIT (GENIE) dynamics model on video tokens.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    g = p.add_argument_group("data")
    g.add_argument("--train_data_dir", default=first_existing("data/sample/train", "data/train_v1.1"),
                   help="Token dataset directory (metadata.json, video.bin, segment_ids.bin) to train on.")
    g.add_argument("--val_data_dir", default=first_existing("data/sample/val", "data/val_v1.1"),
                   help="Token dataset directory for validation (non-overlapping windows).")
    g.add_argument("--window_size", type=int, default=16, help="Frames per training window; must equal config T.")
    g.add_argument("--stride", type=int, default=15, help="Frames between consecutive frames of a window.")
    g.add_argument("--filter_overlaps", action="store_true",
                   help="Use only non-overlapping training windows (validation always does).")
    g.add_argument("--num_workers", type=int, default=None,
                   help="DataLoader worker processes (default: 4 on CUDA, 0 on CPU, where reading is cheap).")

    g = p.add_argument_group("model")
    g.add_argument("--genie_config", default=None,
                   help="GenieConfig JSON (default: genie/configs/sample_world.json, else the tiny test config).")
    g.add_argument("--warmstart_path", default=None,
                   help="Hugging Face checkpoint directory (config.json + model.safetensors) whose weights initialize "
                        "the model; the shapes must match --genie_config.")
    g.add_argument("--use_actions", default=None,
                   help="Comma-separated real action streams (actions/<name>.bin of the datasets, e.g. "
                        "buttons,driving_command) to condition on; sets action_names on top of --genie_config. "
                        "Their mean/std over the training split are stored in the checkpoint's config.json.")
    g.add_argument("--action_step_mean", action="store_true",
                   help="Read each real action row as the mean over the --stride frames from its window frame to the "
                        "next (all that was commanded during the step) instead of the single row of the frame; sets "
                        "action_step_mean on top of --genie_config (evaluation and generation read the checkpoint's).")
    g.add_argument("--use_latent_actions", type=int, default=None, metavar="K",
                   help="Condition on LAM latent actions with codebook size K (ids from actions/latent_action.bin, "
                        "written by lam/label.py); sets num_latent_actions on top of --genie_config.")
    g.add_argument("--resume_from_checkpoint", default=None,
                   help="'latest' (newest complete checkpoint-<step> in --output_dir; starts fresh if there is none) "
                        "or a checkpoint directory: continue that run exactly.")

    g = p.add_argument_group("optimization")
    g.add_argument("--per_device_train_batch_size", type=int, default=4, help="Windows per process per micro-batch.")
    g.add_argument("--per_device_eval_batch_size", type=int, default=4, help="Windows per process per eval batch.")
    g.add_argument("--gradient_accumulation_steps", type=int, default=1, help="Micro-batches per optimizer step.")
    g.add_argument("--optimizer", default="adamw", choices=("adamw", "muon"),
                   help="adamw, or muon: Muon steps (orthogonalized momentum, scaled to AdamW's step size) for the "
                        "transformer's hidden matrices and AdamW for embeddings, heads, biases and norms, with the "
                        "same learning rate, schedule and weight decay (common/muon.py).")
    g.add_argument("--muon_momentum", type=finite_float, default=0.95, help="Muon's (Nesterov) momentum.")
    g.add_argument("--learning_rate", type=finite_float, default=1e-4, help="Peak learning rate (AdamW, and Muon's).")
    g.add_argument("--weight_decay", type=finite_float, default=0.0,
                   help="Decoupled weight decay (matrices and embeddings only).")
    g.add_argument("--adam_beta_1", type=finite_float, default=0.9, help="AdamW beta1.")
    g.add_argument("--adam_beta_2", type=finite_float, default=0.999, help="AdamW beta2.")
    g.add_argument("--adam_eps", type=finite_float, default=1e-8, help="AdamW epsilon.")
    g.add_argument("--lr_scheduler_type", default="linear", choices=LR_SCHEDULES,
                   help="Learning-rate schedule over --max_train_steps (custom_cosine: warmup, then cosine to 10%%).")
    g.add_argument("--num_warmup_steps", type=int, default=0, help="Linear warmup steps (optimizer steps).")
    g.add_argument("--max_train_steps", type=int, default=None,
                   help="Optimizer steps to train; overrides --num_train_epochs.")
    g.add_argument("--num_train_epochs", type=int, default=1, help="Epochs to train when --max_train_steps is unset.")
    g.add_argument("--ema_decay", type=finite_float, default=0.0,
                   help="Keep an exponential moving average of the weights with this decay (e.g. 0.995: about the "
                        "last 200 steps, ramped up from 0.18 over the first steps: common/ema.py) and write it as "
                        "final_checkpt; the periodic validation scores the average too, and each checkpoint-<step>/ "
                        "keeps the raw weights with the average in its ema/ folder, so a resumed run continues "
                        "both. 0 (the default): no average, final_checkpt holds the last step's weights.")
    g.add_argument("--max_grad_norm", type=finite_float, default=1.0,
                   help="Gradient clipping norm (<= 0: no clipping).")
    g.add_argument("--max_nonfinite_steps", type=int, default=5,
                   help="Stop (after saving a checkpoint) when this many steps in a row have a NaN/inf loss or "
                        "gradient; each one is skipped with a warning.")
    g.add_argument("--max_diverged_steps", type=int, default=50,
                   help="Stop with an error when this many optimizer steps in a row have a training loss above "
                        "twice a uniform guess's (2 ln image_vocab_size: 25.0 for 2^18 tokens; a healthy run "
                        "starts below one): the run has diverged, its weights are not saved, and the message "
                        "names the last checkpoint. 0: never stop.")
    g.add_argument("--seed", type=int, default=42, help="Seed of initialization, data order and masking.")
    g.add_argument("--mixed_precision", default="auto", choices=("auto", "no", "bf16"),
                   help="auto: bf16 autocast on CUDA, fp32 on CPU. bf16 on a CPU with native bf16 (avx512_bf16, "
                        "AMX) trains faster than fp32 (benchmarks/bench_train.py --mixed_precision compare); on "
                        "other CPUs it is emulated and slow (a warning says so when the CPU's flags lack it).")
    add_num_threads_arg(g)
    g.add_argument("--no_compile", action="store_true",
                   help="Train eagerly on CUDA too (by default the whole model is torch.compile'd on CUDA: minutes "
                        "of compiling before the first steps, faster steps after; the CPU always trains eagerly).")
    g.add_argument("--gradient_checkpointing", action="store_true",
                   help="Recompute each transformer block in the backward pass instead of keeping its activations: "
                        "about a third more compute for much less activation memory (larger batches on a GPU).")
    g.add_argument("--overfit_first_batch", action="store_true",
                   help="Sanity check: train and validate on the first batch of the training data only.")

    g = p.add_argument_group("evaluation, checkpoints and logging")
    g.add_argument("--output_dir", default="data/genie_model",
                   help="Where checkpoint-<step>/ (full training state) and final_checkpt/ (model) are written.")
    g.add_argument("--eval_every_n_steps", type=int, default=1000, help="Validate every N optimizer steps (0: never).")
    g.add_argument("--max_eval_steps", type=int, default=100,
                   help="Validation batches per process per evaluation (0: the whole validation set).")
    g.add_argument("--checkpointing_steps", default="1000",
                   help="Save the training state every N optimizer steps, 'epoch' for every epoch, or 0 for never "
                        "(the final step is always saved unless 0).")
    g.add_argument("--checkpoints_total_limit", type=int, default=3,
                   help="Keep at most this many checkpoint-<step> directories (0: keep all).")
    g.add_argument("--report_to", default="none", choices=("none", "tensorboard", "wandb"),
                   help="Metrics tracker (logs are also written with `logging`).")

    # Test-suite hooks, hidden from --help: make the loss NaN in these (1-based) optimizer steps, and sleep after
    # each step so that tests can kill a run mid-training.
    p.add_argument("--debug_inject_nan_at_steps", type=int, nargs="*", default=[], help=argparse.SUPPRESS)
    p.add_argument("--debug_step_sleep", type=float, default=0.0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for name in ("window_size", "stride", "per_device_train_batch_size", "per_device_eval_batch_size",
                 "gradient_accumulation_steps", "max_nonfinite_steps"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    check_optimizer_args(p, args, rates=("learning_rate", "adam_eps"),
                         betas=("adam_beta_1", "adam_beta_2", "muon_momentum"))
    if not 0.0 <= args.ema_decay < 1.0:
        p.error(f"--ema_decay must be in [0, 1) (0: no average), got {args.ema_decay}")
    if args.max_diverged_steps < 0:
        p.error(f"--max_diverged_steps must be >= 0, got {args.max_diverged_steps}")
    if args.max_train_steps is not None and args.max_train_steps < 0:
        p.error(f"--max_train_steps must be >= 0, got {args.max_train_steps}")
    if args.use_latent_actions is not None and args.use_latent_actions < 1:
        p.error(f"--use_latent_actions must be >= 1 (the LAM codebook size), got {args.use_latent_actions}")
    if args.use_actions is not None and not all(args.use_actions.split(",")):
        p.error(f"--use_actions must be comma-separated stream names, got {args.use_actions!r}")
    if args.checkpointing_steps != "epoch" and not args.checkpointing_steps.isdigit():
        p.error(f"--checkpointing_steps must be an integer or 'epoch', got {args.checkpointing_steps!r}")
    return args


# ---------------------------------------------------------------- setup

def config_path(path) -> str:
    """--genie_config, else the sample world's config when it exists, else the tiny test config."""
    if path is None:
        path = first_existing(CONFIG_DIR / "sample_world.json", CONFIG_DIR / "tiny_test.json")
    return str(path)


def load_config(path):
    """(GenieConfig, TrainingRecipe) of a --genie_config file (one JSON holds both, as the published one does)."""
    path = config_path(path)
    return GenieConfig.from_pretrained(path), TrainingRecipe.from_pretrained(path)


def build_datasets(args, config: GenieConfig, batch_items: int):
    """(train, val) datasets; with --overfit_first_batch both are the first `batch_items` training windows."""
    train_ds = RawTokenDataset(args.train_data_dir, window_size=args.window_size, stride=args.stride,
                               filter_overlaps=args.filter_overlaps)
    source = f"model config {config_path(args.genie_config)}"
    check_dataset_matches(config, train_ds, args.window_size, source)
    if args.overfit_first_batch:
        subset = Subset(train_ds, range(min(batch_items, len(train_ds))))
        return subset, subset
    val_ds = RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride,
                             filter_overlaps=True)
    check_dataset_matches(config, val_ds, args.window_size, source)
    return train_ds, val_ds


def configure_actions(config: GenieConfig, args, train_ds: RawTokenDataset) -> GenieConfig:
    """Apply --use_actions / --use_latent_actions and fill action_dim and the normalization statistics (mean/std
    over the training split) of the real action streams, unless the config already has them for those streams."""
    names = args.use_actions.split(",") if args.use_actions else config.action_names
    num_latent = config.num_latent_actions if args.use_latent_actions is None else args.use_latent_actions
    step_mean = args.action_step_mean or config.action_step_mean
    if step_mean and not names:
        raise ConfigError("--action_step_mean: no real action streams to average (give --use_actions)")
    changes = {"num_latent_actions": num_latent, "action_step_mean": step_mean}
    if names and (names != config.action_names or config.action_mean is None or step_mean != config.action_step_mean):
        dim = sum(stream_dims(train_ds, names).values())
        mean, std = action_statistics(train_ds, names, step_mean)
        logger.info("conditioning on actions %s (%d values per frame%s); mean %s, std %s from %s", names, dim,
                    ", step means" if step_mean else "", np.round(mean, 3).tolist(), np.round(std, 3).tolist(),
                    train_ds.data_dir)
        changes.update(action_names=names, action_dim=dim, action_mean=mean, action_std=std)
    return dataclasses.replace(config, **changes)


def build_model(config: GenieConfig, warmstart_path) -> STMaskGIT:
    model = STMaskGIT(config)
    model.init_weights()
    if warmstart_path is not None:
        source = STMaskGIT.from_pretrained(warmstart_path)
        state = source.state_dict()
        # opt-in modules the source lacks (action inputs, the copy head: e.g. fine-tuning GENIE_35M with them)
        # start fresh; everything else must match
        for name in ("action_cond", "copy_head"):
            if getattr(source, name) is None and getattr(model, name) is not None:
                state.update({f"{name}.{k}": v for k, v in getattr(model, name).state_dict().items()})
        load_state_dict_checked(model, state, source=f"--warmstart_path {warmstart_path}")
    return model


def build_optimizer(model, args, fused: bool) -> torch.optim.Optimizer:
    """--optimizer over the model: AdamW, or Muon for the transformer's hidden matrices and AdamW for the rest."""
    return muon.build_optimizer(model.parameters(), model.decoder.parameters(), args.optimizer,
                                lr=args.learning_rate, weight_decay=args.weight_decay,
                                betas=(args.adam_beta_1, args.adam_beta_2), eps=args.adam_eps,
                                momentum=args.muon_momentum, fused=fused)


def batch_seed(*keys: int) -> int:
    """A well-mixed 32-bit seed for one micro-batch's masking, from (seed, process, step, micro-batch)."""
    return int(np.random.SeedSequence([k & 0xFFFFFFFF for k in keys]).generate_state(1)[0])


def keep_list(items):
    """DataLoader collate_fn: hand the items to the main process, which applies the (seeded) MaskGIT collator."""
    return items


class StopSignal:
    """Remembers a SIGTERM so that the loop can save a checkpoint at the next step boundary."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame):
        self.requested = True  # only a flag: the handler may interrupt anything, logging included

    def __enter__(self):
        self._previous = signal.signal(signal.SIGTERM, self._handle)
        return self

    def __exit__(self, *exc):
        signal.signal(signal.SIGTERM, self._previous)
        return False


# ---------------------------------------------------------------- the loop

class Trainer:
    def __init__(self, args, accelerator: Accelerator, config: GenieConfig, recipe: TrainingRecipe):
        self.args, self.accelerator, self.config, self.recipe = args, accelerator, config, recipe
        self.device = accelerator.device
        self.rank, self.world = accelerator.process_index, accelerator.num_processes
        B, ga = args.per_device_train_batch_size, args.gradient_accumulation_steps
        self.train_ds, self.val_ds = build_datasets(args, config, B * ga * self.world)
        raw_train_ds, raw_val_ds = (getattr(ds, "dataset", ds) for ds in (self.train_ds, self.val_ds))  # Subset
        self.config = config = configure_actions(config, args, raw_train_ds)
        for ds in (raw_train_ds, raw_val_ds):
            prepare_action_streams(config, ds)
        lam_stride = latent_action_sidecar(raw_train_ds).get("latent_action_stride") if config.num_latent_actions \
            else None
        if lam_stride not in (None, args.stride):
            logger.warning("%s: the latent actions connect frames %d apart but windows use --stride %d; each frame "
                           "is conditioned on a transition of another length", raw_train_ds.data_dir, lam_stride,
                           args.stride)
        self.sampler = ResumableBatchSampler(len(self.train_ds), B, self.world, self.rank, seed=args.seed,
                                             shuffle=not args.overfit_first_batch)
        self.steps_per_epoch = self.sampler.batches_per_epoch // ga
        if self.steps_per_epoch == 0:
            raise TrainingError(f"{args.train_data_dir}: {len(self.train_ds)} training windows are too few for one "
                                f"optimizer step of {B} x {ga} (accumulation) x {self.world} (processes) windows")
        self.max_steps = (args.max_train_steps if args.max_train_steps is not None
                          else args.num_train_epochs * self.steps_per_epoch)
        every = args.checkpointing_steps
        self.checkpoint_every = self.steps_per_epoch if every == "epoch" else int(every)
        self.tokens_per_step = B * ga * self.world * config.T * config.S

        self.model = build_model(config, args.warmstart_path).to(self.device)
        self.model.decoder.gradient_checkpointing = args.gradient_checkpointing
        # torch's fused AdamW kernel exists for CUDA and CPU (~15x faster than the per-tensor loop on CPU)
        self.optimizer = build_optimizer(self.model, args, fused=self.device.type in ("cuda", "cpu"))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lr_multiplier(args.lr_scheduler_type, args.num_warmup_steps, self.max_steps))
        self.step = 0
        self.consecutive_nonfinite = 0
        self.consecutive_diverged = 0
        self.diverged_loss = 2 * math.log(config.image_vocab_size)
        self.last_saved_step = None
        resumed = self.resume()
        self.ema = self.weight_average(resumed) if args.ema_decay > 0 else None
        self.ddp_model, self.ddp_optimizer = accelerator.prepare(self.model, self.optimizer)
        if self.use_compile():
            self.ddp_model = torch.compile(self.ddp_model)

    def use_compile(self) -> bool:
        return not self.args.no_compile and self.device.type == "cuda"

    # ---- checkpoints
    def trainer_state(self) -> dict:
        epoch, batch = divmod(self.step, self.steps_per_epoch)
        return {"step": self.step, "epoch": epoch, "batch_in_epoch": batch * self.args.gradient_accumulation_steps,
                "steps_per_epoch": self.steps_per_epoch, "scheduler": self.scheduler.state_dict(),
                "world_size": self.world, "seed": self.args.seed, "num_train_windows": len(self.train_ds),
                "per_device_train_batch_size": self.args.per_device_train_batch_size,
                "gradient_accumulation_steps": self.args.gradient_accumulation_steps,
                "args": dict(vars(self.args)), **({"ema_updates": self.ema.updates} if self.ema else {})}

    def save_checkpoint(self) -> None:
        """All processes call this (RNG states are gathered); only the main process writes."""
        rng_states = gather_object([capture_rng_state()]) if self.world > 1 else [capture_rng_state()]
        if self.accelerator.is_main_process:
            path = checkpoint_dir(self.args.output_dir, self.step)
            save_training_checkpoint(path, self.model, self.optimizer, self.trainer_state(), rng_states,
                                     model_kwargs={"recipe": self.recipe},
                                     extra_models={EMA_DIR: self.ema.model} if self.ema else None)
            prune_checkpoints(self.args.output_dir, self.args.checkpoints_total_limit)
            logger.info("saved training state to %s", path)
        self.last_saved_step = self.step
        self.accelerator.wait_for_everyone()

    def resume(self) -> Optional[tuple]:
        """Load --resume_from_checkpoint's training state; returns (its path, its trainer state), or None."""
        path = resolve_resume_path(self.args.output_dir, self.args.resume_from_checkpoint)
        if path is None:
            if self.args.resume_from_checkpoint == "latest":
                logger.info("no complete checkpoint in %s yet: starting from scratch", self.args.output_dir)
            return None
        ckpt = load_training_checkpoint(path)
        differing = sorted(k for k, v in self.config.to_dict().items() if ckpt["config"].get(k) != v)
        if differing:
            raise TrainingStateError(f"{path / 'config.json'}: the checkpoint's model config differs from "
                                     f"--genie_config in {differing}")
        state = ckpt["trainer"]
        saved_optimizer = state.get("args", {}).get("optimizer", "adamw")  # runs from before --optimizer used AdamW
        if saved_optimizer != self.args.optimizer:
            raise TrainingStateError(f"{path}: the run was trained with --optimizer {saved_optimizer}, not "
                                     f"{self.args.optimizer}; resume it with the same optimizer")
        load_model(self.model, str(ckpt["model_path"]), device=str(self.device))
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step = self.last_saved_step = state["step"]
        same_order = all(state.get(k) == v for k, v in (
            ("world_size", self.world), ("seed", self.args.seed), ("num_train_windows", len(self.train_ds)),
            ("per_device_train_batch_size", self.args.per_device_train_batch_size),
            ("gradient_accumulation_steps", self.args.gradient_accumulation_steps)))
        if not same_order:
            logger.warning("resuming with a different seed, dataset, batch size or process count than %s: training "
                           "continues from step %d but the data order differs from the interrupted run", path,
                           self.step)
        rng = ckpt["rng"]
        restore_rng_state(rng[self.rank] if len(rng) == self.world else rng[0])
        logger.info("resumed from %s at step %d (epoch %d)", path, self.step, state["epoch"])
        return path, state

    def weight_average(self, resumed: Optional[tuple]) -> WeightAverage:
        """The --ema_decay average, from the (resumed) weights, continuing the resumed checkpoint's own when it has
        one."""
        average = WeightAverage(self.model, self.args.ema_decay)
        if resumed is not None:
            path, state = resumed
            average_path = path / EMA_DIR / "model.safetensors"
            if average_path.is_file() and "ema_updates" in state:
                load_model(average.model, str(average_path), device=str(self.device))
                average.updates = state["ema_updates"]
            else:
                logger.warning("%s holds no weight average: --ema_decay starts one from its weights at step %d",
                               path, self.step)
        return average

    def final_model(self) -> STMaskGIT:
        """What final_checkpt gets and validation scores: the weight average, or the plain module (no DDP hooks,
        no recompilation for eval mode)."""
        return self.ema.model if self.ema else self.model

    # ---- data
    def epoch_batches(self, epoch: int, start_batch: int):
        self.sampler.set_epoch(epoch, start_batch)
        loader = DataLoader(self.train_ds, batch_sampler=self.sampler, collate_fn=keep_list,
                            num_workers=self.num_workers(), pin_memory=self.device.type == "cuda",
                            generator=torch.Generator())  # own generator: worker seeding leaves the global RNG alone
        return iter(loader)

    def num_workers(self) -> int:
        if self.args.num_workers is not None:
            return self.args.num_workers
        return 4 if self.device.type == "cuda" else 0

    def collate(self, items, seed: int) -> MaskGITBatch:
        return get_maskgit_collator(self.config, self.recipe, seed=seed)(items).to(self.device, non_blocking=True)

    # ---- one optimizer step
    def forward_backward(self, micro_batches) -> torch.Tensor:
        """Accumulate gradients over the micro-batches; returns the mean loss (detached)."""
        ga = len(micro_batches)
        inject = (self.step + 1) in self.args.debug_inject_nan_at_steps
        loss_sum = torch.zeros((), device=self.device)
        for i, batch in enumerate(micro_batches):
            sync = contextlib.nullcontext() if i == ga - 1 else self.accelerator.no_sync(self.ddp_model)
            with sync:
                loss = self.ddp_model(batch, self.recipe).loss / ga
                if inject:
                    loss = loss * float("nan")
                self.accelerator.backward(loss)
            loss_sum += loss.detach().float()
        return loss_sum

    def optimizer_step(self, loss: torch.Tensor, stop_requested: bool):
        """Clip, check for NaN/inf and a diverged loss (agreed on by all processes), step.
        Returns (grad_norm, finite, stop, diverged)."""
        max_norm = self.args.max_grad_norm if self.args.max_grad_norm > 0 else float("inf")
        grad_norm = self.accelerator.clip_grad_norm_(self.ddp_model.parameters(), max_norm)
        flags = torch.stack([(~torch.isfinite(loss)) | (~torch.isfinite(grad_norm)),
                             torch.tensor(stop_requested, device=self.device),
                             loss > self.diverged_loss]).float()
        if self.world > 1:
            flags = self.accelerator.reduce(flags, reduction="sum")
        finite, stop, diverged = bool(flags[0] == 0), bool(flags[1] > 0), bool(flags[2] > 0)
        if finite:
            self.ddp_optimizer.step()
            if self.ema is not None:
                self.ema.update(self.model)
        self.ddp_optimizer.zero_grad(set_to_none=True)
        self.scheduler.step()  # the schedule follows the data position, skipped steps included
        return grad_norm, finite, stop, diverged

    def handle_nonfinite(self, finite: bool, loss: float) -> None:
        if finite:
            self.consecutive_nonfinite = 0
            return
        self.consecutive_nonfinite += 1
        logger.warning("step %d: non-finite loss (%s) or gradient; step skipped (%d in a row, limit %d)",
                       self.step, loss, self.consecutive_nonfinite, self.args.max_nonfinite_steps)
        if self.consecutive_nonfinite >= self.args.max_nonfinite_steps:
            self.save_checkpoint()
            raise TrainingError(
                f"{self.consecutive_nonfinite} optimizer steps in a row had a NaN/inf loss or gradient; stopped. "
                f"The weights of the last good step are saved in {checkpoint_dir(self.args.output_dir, self.step)} "
                f"(lower --learning_rate, check the data, or resume from it to skip the bad batches)")

    def handle_divergence(self, diverged: bool, loss: float) -> None:
        """Count the steps in a row whose loss is above twice a uniform guess's (on any process, so that all
        processes stop together); too many stop the run."""
        self.consecutive_diverged = self.consecutive_diverged + 1 if diverged else 0
        limit = self.args.max_diverged_steps
        if limit == 0 or self.consecutive_diverged < limit:
            return
        first = self.step - self.consecutive_diverged + 1
        saved = list_checkpoints(self.args.output_dir)
        last = f"the last checkpoint is {saved[-1][1]}" if saved else "no checkpoint was saved"
        raise TrainingError(
            f"training diverged: the loss stayed above {self.diverged_loss:.1f} (twice a uniform guess over "
            f"{self.config.image_vocab_size} tokens) from step {first} to step {self.step} (loss {loss:.4g}); "
            f"these weights are not saved and {last}. Lower --learning_rate or lengthen --num_warmup_steps")

    # ---- evaluation
    @torch.no_grad()
    def evaluate(self) -> dict:
        """Teacher-forced masked loss/accuracy on the same (seeded) validation batches and masks every time."""
        sampler = ResumableBatchSampler(len(self.val_ds), self.args.per_device_eval_batch_size, self.world,
                                        self.rank, seed=0, drop_last=False)
        loader = DataLoader(self.val_ds, batch_sampler=sampler, collate_fn=keep_list, num_workers=0)
        collator = get_maskgit_collator(self.config, self.recipe, seed=self.args.seed)
        model = self.final_model().eval()
        totals = torch.zeros(3, dtype=torch.float64, device=self.device)  # loss * B, acc * B, B
        for i, items in enumerate(loader):
            if 0 < self.args.max_eval_steps <= i:
                break
            batch = collator(items).to(self.device, non_blocking=True)
            with self.accelerator.autocast():
                out = model(batch, self.recipe)
            n = len(items)
            totals += torch.stack([out.loss.double() * n, torch.as_tensor(out.acc).double().to(self.device) * n,
                                   torch.tensor(n, dtype=torch.float64, device=self.device)])
        self.model.train()
        if self.world > 1:
            totals = self.accelerator.reduce(totals, reduction="sum")
        return {"val_loss": (totals[0] / totals[2]).item(), "val_acc": (totals[1] / totals[2]).item()}

    def log_eval(self) -> None:
        metrics = self.evaluate()
        logger.info("step %d: val_loss %.4f val_acc %.4f", self.step, metrics["val_loss"], metrics["val_acc"])
        self.accelerator.log(metrics, step=self.step)

    # ---- main loop
    def train(self) -> None:
        args = self.args
        logger.info("training %d steps (%d per epoch) of %d tokens; %d processes; starting at step %d",
                    self.max_steps, self.steps_per_epoch, self.tokens_per_step, self.world, self.step)
        self.ddp_model.train()
        bar = tqdm(total=self.max_steps, initial=self.step, disable=not self.accelerator.is_local_main_process,
                   desc="train", dynamic_ncols=True)
        # logging_redirect_tqdm: log lines go above the progress bar instead of through it.
        with StopSignal() as stop_signal, logging_redirect_tqdm():  # SIGTERM after the last step: saves finish
            while self.step < self.max_steps:
                epoch, batch_in_epoch = divmod(self.step, self.steps_per_epoch)
                batches = self.epoch_batches(epoch, batch_in_epoch * args.gradient_accumulation_steps)
                steps_this_epoch = min(self.steps_per_epoch - batch_in_epoch, self.max_steps - self.step)
                for _ in range(steps_this_epoch):
                    if self.train_one_step(batches, bar, stop_signal):
                        bar.close()
                        return
            bar.close()
            if args.eval_every_n_steps > 0 and self.step % args.eval_every_n_steps:
                self.log_eval()
            if self.checkpoint_every > 0 and self.last_saved_step != self.step:
                self.save_checkpoint()
            self.save_final()

    def train_one_step(self, batches, bar, stop_signal) -> bool:
        """One optimizer step; returns True when the run must stop now (SIGTERM)."""
        args, t0 = self.args, time.perf_counter()
        ga = args.gradient_accumulation_steps
        micro_batches = [self.collate(next(batches), batch_seed(args.seed, self.rank, self.step, i))
                         for i in range(ga)]
        loss = self.forward_backward(micro_batches)
        grad_norm, finite, stop, diverged = self.optimizer_step(loss, stop_signal.requested)
        self.step += 1
        loss_value = loss.item()
        self.handle_nonfinite(finite, loss_value)
        if finite:
            self.handle_divergence(diverged, loss_value)
        lr = self.scheduler.get_last_lr()[0]
        tokens_per_s = self.tokens_per_step / (time.perf_counter() - t0)
        bar.update(1)
        bar.set_postfix(loss=f"{loss_value:.4f}", lr=f"{lr:.2e}", tok_s=f"{tokens_per_s:,.0f}")
        self.accelerator.log({"train_loss": loss_value, "lr": lr, "grad_norm": float(grad_norm),
                              "tokens_per_s": tokens_per_s}, step=self.step)
        if args.eval_every_n_steps > 0 and self.step % args.eval_every_n_steps == 0:
            self.log_eval()
        if stop:
            if self.last_saved_step != self.step:
                self.save_checkpoint()
            if self.accelerator.is_main_process:
                logger.warning("SIGTERM: stopped at step %d with its training state saved; resume with "
                               "--resume_from_checkpoint latest", self.step)
            return True
        if self.checkpoint_every > 0 and self.step % self.checkpoint_every == 0:
            self.save_checkpoint()
        if args.debug_step_sleep > 0:
            time.sleep(args.debug_step_sleep)
        return False

    def save_final(self) -> None:
        if self.accelerator.is_main_process:
            path = Path(self.args.output_dir) / "final_checkpt"
            with atomic_directory(path, "the final model") as tmp:
                self.final_model().save_pretrained(tmp, recipe=self.recipe)
            if self.ema:
                logger.info("saved the weight average of %d steps (--ema_decay %g) to %s; the last step's own "
                            "weights are in the newest checkpoint-<step>/ when checkpointing is on",
                            self.ema.updates, self.ema.decay, path)
            else:
                logger.info("saved the final model to %s", path)
        self.accelerator.wait_for_everyone()


def check_tracker_installed(report_to: str) -> None:
    """accelerate silently drops a tracker whose package is missing; say so instead."""
    packages = {"none": [], "tensorboard": ["tensorboard", "tensorboardX"], "wandb": ["wandb"]}[report_to]
    if packages and not any(importlib.util.find_spec(p) for p in packages):
        raise TrainingError(f"--report_to {report_to} needs the {packages[0]} package: pip install {packages[0]}")


def setup_process_logging(accelerator: Accelerator) -> None:
    """Only the main process logs progress; the others log warnings and errors."""
    level = logging.INFO if accelerator.is_main_process else logging.WARNING
    setup_logging(level)
    logger.setLevel(level)


def run(args) -> None:
    apply_cpu_settings(args.num_threads)
    mixed = args.mixed_precision
    if mixed == "auto":
        mixed = "bf16" if torch.cuda.is_available() else "no"
    check_tracker_installed(args.report_to)
    # A multi-process launch on a machine without CUDA (torchrun, `accelerate launch --multi_gpu`) must ask for
    # CPU explicitly: only then does accelerate set up DDP over gloo instead of running independent copies.
    launched_world = int(os.environ.get("WORLD_SIZE", "0"))
    accelerator = Accelerator(mixed_precision=mixed, log_with=None if args.report_to == "none" else args.report_to,
                              project_dir=args.output_dir, cpu=launched_world > 1 and not torch.cuda.is_available())
    setup_process_logging(accelerator)
    if mixed == "bf16" and accelerator.device.type == "cpu" and cpu_has_native_bf16() is False:
        logger.warning(f"--mixed_precision bf16 on a CPU without native bf16 ({NO_NATIVE_BF16}): bf16 is emulated "
                       "there and usually slower than fp32 (--mixed_precision no)")
    if launched_world and launched_world != accelerator.num_processes:
        raise TrainingError(f"launched as {launched_world} processes (WORLD_SIZE) but accelerate set up "
                            f"{accelerator.num_processes}; each process would train alone")
    if accelerator.num_processes == 1 and os.environ.get("ACCELERATE_USE_CPU", "").lower() == "true" \
            and "MASTER_ADDR" in os.environ:
        logger.warning("`accelerate launch --cpu --num_processes N` starts a single process unless MPI is set up "
                       "(--mpirun_hostfile); for N CPU processes use `accelerate launch --multi_gpu "
                       "--num_processes N train.py` or `torchrun --nproc_per_node N train.py` on a machine without "
                       "GPUs. Training with 1 process.")
    if accelerator.device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    set_seed(args.seed)
    config, recipe = load_config(args.genie_config)
    if accelerator.is_main_process:
        Path(args.output_dir).mkdir(parents=True, exist_ok=True)
        remove_stale_temp_dirs(args.output_dir)
    accelerator.wait_for_everyone()
    trainer = Trainer(args, accelerator, config, recipe)
    accelerator.init_trackers("genie", config={k: v if isinstance(v, (int, float, str, bool)) else str(v)
                                               for k, v in {**vars(args), **trainer.config.to_dict(),
                                                             **recipe.to_dict()}.items()})
    try:
        trainer.train()
    finally:
        # Free the DDP wrapper (its reducer holds the process group) while the interpreter is whole, then destroy
        # the group: left to interpreter shutdown, gloo's threads can abort a finished run (SIGABRT, exit code 1).
        del trainer
        accelerator.free_memory()
        accelerator.end_training()


def main(argv=None) -> None:
    args = parse_args(argv)
    try:
        run(args)
    except WriteError as e:  # full disk / I/O error: say what failed and where the run can resume from
        sys.exit(f"train.py: error: {e}; {resume_hint(args.output_dir)}")
    except (InputError, TrainingError, OSError) as e:  # bad input, or a run that cannot go on: one line
        sys.exit(f"train.py: error: {e}")


if __name__ == "__main__":
    main()
