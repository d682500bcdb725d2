#!/usr/bin/env python
"""Train the GENIE dynamics model (STMaskGIT) on a token dataset, with accelerate (CPU, one GPU, many GPUs/nodes).

    python train.py --recipe recipes/sample_world.json --output_dir data/genie_model   # the main command's run
    python train.py --recipe recipes/sample_world.json --max_train_steps 50 ...  # a flag overrides the recipe's value
    python train.py --genie_config genie/configs/sample_world.json --output_dir data/genie_model   # flags alone
    python train.py ... --resume_from_checkpoint latest       # continue a killed/preempted run
    python train.py ... --use_actions buttons,driving_command  # condition on real actions (actions/<name>.bin)
    python train.py ... --use_actions buttons,driving_command --action_step_mean  # ... averaged over each window step
    python train.py ... --use_latent_actions 8                 # condition on LAM latent actions (latent_action.bin)
    python train.py ... --ema_decay 0.995                      # final_checkpt: a moving average of the weights
    accelerate launch --multi_gpu --num_processes 2 train.py ...   # DDP: NCCL on GPUs, gloo on a CPU-only machine
    torchrun --nproc_per_node 2 train.py ...                       # the same without accelerate's launcher

(`accelerate launch --cpu --num_processes N` starts a single process unless MPI is configured.)

A run's recipe is one file (recipes/*.json, training/recipe.py): the model, these flags' values and how the trained
model is sampled. Every checkpoint keeps the resolved recipe as recipe.json and the decoding as decoding.json.

The model owns its loss (model(batch, recipe).loss, genie/model.py); this script owns the loop. The training state
around it (checkpoints, resume, the weight average, the NaN/inf and divergence guards) is training/trainer.py's.

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
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.utils import set_seed
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

import genie.configs
from common import muon
from common.cli import (NO_NATIVE_BF16, add_num_threads_arg, apply_cpu_settings, check_optimizer_args,
                        cpu_has_native_bf16, finite_float, setup_logging)
from common.errors import InputError, TrainingError, WriteError
from common.files import remove_stale_temp_dirs
from common.schedules import LR_SCHEDULES, lr_multiplier
from common.train_state import ResumableBatchSampler, resume_hint
from data import RawTokenDataset
from genie.checkpoint import load_state_dict_checked
from genie.config import ConfigError, GenieConfig, TrainingRecipe, check_dataset_matches
from genie.decoding import DecodingConfig
from genie.model import MaskGITBatch, STMaskGIT
from training.action_streams import action_statistics, latent_action_sidecar, prepare_action_streams, stream_dims
from training.batches import batch_seed, keep_list
from training.masking import get_maskgit_collator
from training.recipe import RunRecipe, load_model_config, load_recipe, resolved_recipe
from training.signals import StopSignal
from training.trainer import SavedWith, TrainConfig, Trainer
from training.validation import validate

logger = logging.getLogger("train")

CONFIG_DIR = Path(genie.configs.__file__).parent


def first_existing(*paths) -> str:
    """The first path that exists, else the last one (so the error message names the canonical location)."""
    for p in paths:
        if Path(p).exists():
            return str(p)
    return str(paths[-1])


# ---------------------------------------------------------------- flags

def parse_args(argv=None) -> argparse.Namespace:
    p = build_parser()
    recipe_path = recipe_flag(argv)
    if recipe_path is not None:
        try:
            p.set_defaults(**recipe_defaults(p, load_recipe(recipe_path)))
        except (ConfigError, FileNotFoundError) as e:
            p.error(str(e))
    args = p.parse_args(argv)
    check_args(p, args)
    return args


def recipe_flag(argv) -> Optional[str]:
    """--recipe alone, read before the other flags: its values must be in place as their defaults first."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--recipe", default=None)
    return pre.parse_known_args(argv)[0].recipe


def recipe_defaults(p: argparse.ArgumentParser, recipe: RunRecipe) -> dict:
    """The recipe's "train" values as parser defaults, each checked and converted as its flag's value would be."""
    actions = {}
    for action in p._actions:  # argparse has no public index of its flags by name
        if action.option_strings and action.help != argparse.SUPPRESS and action.dest not in ("help", "recipe"):
            actions.setdefault(action.dest, action)  # --no_compile and --compile share one destination
    defaults = {}
    for key, value in recipe.train.items():
        if key not in actions:
            raise ConfigError(f"{recipe.path}: unknown train.py flag {key!r} in \"train\" (known: {sorted(actions)})")
        defaults[key] = flag_value(actions[key], value, f"{recipe.path}: train.{key}")
    return defaults


def flag_value(action: argparse.Action, value, where: str):
    """A recipe's JSON value of a flag, as the flag's own parsing would give it; ConfigError naming `where`."""
    if action.nargs == 0:  # a switch (store_true)
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: must be true or false, got {value!r}")
        return value
    if value is None:
        if action.default is None:
            return None
        raise ConfigError(f"{where}: must be set (null is not a value of {action.option_strings[0]})")
    if isinstance(value, (bool, list, dict)):
        raise ConfigError(f"{where}: must be a number or a string, got {value!r}")
    try:
        converted = action.type(str(value)) if action.type else str(value)
    except (ValueError, TypeError, argparse.ArgumentTypeError) as e:
        raise ConfigError(f"{where}: {value!r} is not a value of {action.option_strings[0]} ({e})") from None
    if action.choices is not None and converted not in action.choices:
        raise ConfigError(f"{where}: must be one of {list(action.choices)}, got {converted!r}")
    return converted


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description="Train a spatio-temporal MaskGIT (GENIE) dynamics model on video tokens.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--recipe", default=None, metavar="FILE",
                   help="A run recipe (recipes/*.json: model, train.py settings, decoding; training/recipe.py): its "
                        "\"train\" values become these flags' defaults (a flag given here overrides one), its "
                        "\"model\" the model config unless --genie_config is given, and its \"decoding\" is saved "
                        "with every checkpoint (decoding.json). Without it: the defaults shown here and the default "
                        "decoding.")
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
                   help="GenieConfig JSON, or a run recipe whose \"model\" is taken (default: --recipe's model, else "
                        "genie/configs/sample_world.json, else the tiny test config).")
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
    g.add_argument("--compile", dest="no_compile", action="store_false",
                   help="torch.compile on CUDA, as without --no_compile: turns off a recipe's no_compile.")
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
    return p


def check_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Usage errors the flags' types cannot catch (a recipe's values included)."""
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


# ---------------------------------------------------------------- setup

def model_config(args, recipe: Optional[RunRecipe]) -> Tuple[GenieConfig, TrainingRecipe, str]:
    """(architecture, masking recipe, where they come from): --genie_config, else the recipe's model, else the
    sample world's config when it exists, else the tiny test config."""
    if args.genie_config is None and recipe is not None:
        return (*recipe.model_config(), f"the model of recipe {recipe.path}")
    path = args.genie_config or first_existing(CONFIG_DIR / "sample_world.json", CONFIG_DIR / "tiny_test.json")
    return (*load_model_config(path), f"model config {path}")


def build_datasets(args, config: GenieConfig, batch_items: int, source: str) -> Tuple[Dataset, Dataset]:
    """(train, val) datasets; with --overfit_first_batch both are the first `batch_items` training windows."""
    train_ds = RawTokenDataset(args.train_data_dir, window_size=args.window_size, stride=args.stride,
                               filter_overlaps=args.filter_overlaps)
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


def prepare_actions(config: GenieConfig, args, train_ds: Dataset, val_ds: Dataset) -> GenieConfig:
    """The config with its action inputs filled in, and the datasets set to read them."""
    raw_train_ds, raw_val_ds = (getattr(ds, "dataset", ds) for ds in (train_ds, val_ds))  # a Subset's dataset
    config = configure_actions(config, args, raw_train_ds)
    for ds in (raw_train_ds, raw_val_ds):
        prepare_action_streams(config, ds)
    lam_stride = latent_action_sidecar(raw_train_ds).get("latent_action_stride") if config.num_latent_actions \
        else None
    if lam_stride not in (None, args.stride):
        logger.warning("%s: the latent actions connect frames %d apart but windows use --stride %d; each frame "
                       "is conditioned on a transition of another length", raw_train_ds.data_dir, lam_stride,
                       args.stride)
    return config


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


def check_decoding(config: GenieConfig, decoding: DecodingConfig, recipe: Optional[RunRecipe], source: str) -> None:
    """The recipe's decoding must suit the model before hours of training, not when the first checkpoint is saved."""
    if decoding.copy_bias and not config.copy_radius:
        raise ConfigError(f"{recipe.path if recipe else 'decoding'}: decoding.copy_bias {decoding.copy_bias} needs a "
                          f"model with a copy head (copy_radius), and {source} has none; give it a recipe whose "
                          f"decoding has copy_bias 0")


def build_optimizer(model, args, fused: bool) -> torch.optim.Optimizer:
    """--optimizer over the model: AdamW, or Muon for the transformer's hidden matrices and AdamW for the rest."""
    return muon.build_optimizer(model.parameters(), model.decoder.parameters(), args.optimizer,
                                lr=args.learning_rate, weight_decay=args.weight_decay,
                                betas=(args.adam_beta_1, args.adam_beta_2), eps=args.adam_eps,
                                momentum=args.muon_momentum, fused=fused)


def train_config(args, steps_per_epoch: int) -> TrainConfig:
    every = args.checkpointing_steps
    return TrainConfig(
        output_dir=args.output_dir, seed=args.seed, optimizer=args.optimizer,
        per_device_train_batch_size=args.per_device_train_batch_size,
        gradient_accumulation_steps=args.gradient_accumulation_steps, max_grad_norm=args.max_grad_norm,
        max_nonfinite_steps=args.max_nonfinite_steps, max_diverged_steps=args.max_diverged_steps,
        checkpoint_every=steps_per_epoch if every == "epoch" else int(every),
        checkpoints_total_limit=args.checkpoints_total_limit, ema_decay=args.ema_decay, flags=dict(vars(args)))


@dataclass
class TrainData:
    """The training windows in their resumable order, and the validation windows."""
    train: Dataset
    val: Dataset
    sampler: ResumableBatchSampler
    steps_per_epoch: int


def epoch_batches(data: TrainData, epoch: int, start_batch: int, num_workers: int, device: torch.device):
    """An iterator over the epoch's micro-batches (lists of windows), from `start_batch` on."""
    data.sampler.set_epoch(epoch, start_batch)
    loader = DataLoader(data.train, batch_sampler=data.sampler, collate_fn=keep_list, num_workers=num_workers,
                        pin_memory=device.type == "cuda",
                        generator=torch.Generator())  # own generator: worker seeding leaves the global RNG alone
    return iter(loader)


# ---------------------------------------------------------------- the loop

def forward_backward(ddp_model, micro_batches, recipe: TrainingRecipe, accelerator: Accelerator,
                     inject_nan: bool) -> torch.Tensor:
    """Accumulate gradients over the micro-batches (gradients synced across processes on the last one only);
    returns the mean loss, a detached 0-d tensor."""
    ga = len(micro_batches)
    loss_sum = torch.zeros((), device=accelerator.device)
    for i, batch in enumerate(micro_batches):
        sync = contextlib.nullcontext() if i == ga - 1 else accelerator.no_sync(ddp_model)
        with sync:
            loss = ddp_model(batch, recipe).loss / ga
            if inject_nan:
                loss = loss * float("nan")
            accelerator.backward(loss)
        loss_sum += loss.detach().float()
    return loss_sum


def train(args, accelerator: Accelerator, trainer: Trainer, data: TrainData, config: GenieConfig,
          recipe: TrainingRecipe, max_steps: int) -> None:
    """Optimizer steps from the trainer's step (0, or where the resumed run stopped) to max_steps, validating and
    saving on the way; then the last validation and checkpoint, and final_checkpt. SIGTERM: a checkpoint, then
    return."""
    ga, rank, device = args.gradient_accumulation_steps, accelerator.process_index, accelerator.device
    tokens_per_step = args.per_device_train_batch_size * ga * accelerator.num_processes * config.T * config.S
    num_workers = args.num_workers if args.num_workers is not None else (4 if device.type == "cuda" else 0)
    logger.info("training %d steps (%d per epoch) of %d tokens; %d processes; starting at step %d",
                max_steps, data.steps_per_epoch, tokens_per_step, accelerator.num_processes, trainer.step)

    def log_validation():
        metrics = validate(trainer.final_model(), data.val, config, recipe, accelerator,
                           args.per_device_eval_batch_size, args.max_eval_steps, args.seed)
        logger.info("step %d: val_loss %.4f val_acc %.4f", trainer.step, metrics["val_loss"], metrics["val_acc"])
        accelerator.log(metrics, step=trainer.step)

    def collate(items, seed: int) -> MaskGITBatch:
        return get_maskgit_collator(config, recipe, seed=seed)(items).to(device, non_blocking=True)

    trainer.ddp_model.train()
    bar = tqdm(total=max_steps, initial=trainer.step, disable=not accelerator.is_local_main_process, desc="train",
               dynamic_ncols=True)
    # StopSignal spans the final saves too, so that a SIGTERM then lets them finish; logging_redirect_tqdm: log
    # lines go above the progress bar instead of through it
    with StopSignal() as stop_signal, logging_redirect_tqdm(), contextlib.closing(bar):
        while trainer.step < max_steps:
            epoch, batch_in_epoch = divmod(trainer.step, data.steps_per_epoch)
            batches = epoch_batches(data, epoch, batch_in_epoch * ga, num_workers, device)
            for _ in range(min(data.steps_per_epoch - batch_in_epoch, max_steps - trainer.step)):
                t0 = time.perf_counter()
                micro_batches = [collate(next(batches), batch_seed(args.seed, rank, trainer.step, i))
                                 for i in range(ga)]
                loss = forward_backward(trainer.ddp_model, micro_batches, recipe, accelerator,
                                        inject_nan=(trainer.step + 1) in args.debug_inject_nan_at_steps)
                loss, grad_norm, stop = trainer.optimizer_step(loss, stop_signal.requested)

                tokens_per_s = tokens_per_step / (time.perf_counter() - t0)
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4f}", lr=f"{trainer.lr:.2e}", tok_s=f"{tokens_per_s:,.0f}")
                accelerator.log({"train_loss": loss, "lr": trainer.lr, "grad_norm": grad_norm,
                                 "tokens_per_s": tokens_per_s}, step=trainer.step)
                if args.eval_every_n_steps > 0 and trainer.step % args.eval_every_n_steps == 0:
                    log_validation()
                if stop:
                    trainer.save_if_unsaved()
                    if accelerator.is_main_process:
                        logger.warning("SIGTERM: stopped at step %d with its training state saved; resume with "
                                       "--resume_from_checkpoint latest", trainer.step)
                    return
                if trainer.checkpoint_due():
                    trainer.save_checkpoint()
                if args.debug_step_sleep > 0:
                    time.sleep(args.debug_step_sleep)
        bar.close()
        if args.eval_every_n_steps > 0 and trainer.step % args.eval_every_n_steps:
            log_validation()
        if trainer.cfg.checkpoint_every > 0:
            trainer.save_if_unsaved()
        trainer.save_final()


# ---------------------------------------------------------------- main

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


def make_accelerator(args) -> Accelerator:
    """accelerate for this launch (one process, or each process of a DDP launch), with the run's precision."""
    mixed = args.mixed_precision
    if mixed == "auto":
        mixed = "bf16" if torch.cuda.is_available() else "no"
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
    return accelerator


def run(args) -> None:
    apply_cpu_settings(args.num_threads)
    check_tracker_installed(args.report_to)
    accelerator = make_accelerator(args)
    set_seed(args.seed)
    run_recipe = load_recipe(args.recipe) if args.recipe else None
    config, recipe, source = model_config(args, run_recipe)
    decoding = run_recipe.decoding if run_recipe else DecodingConfig()
    check_decoding(config, decoding, run_recipe, source)
    if accelerator.is_main_process:
        Path(args.output_dir).mkdir(parents=True, exist_ok=True)
        remove_stale_temp_dirs(args.output_dir)
    accelerator.wait_for_everyone()

    world, device = accelerator.num_processes, accelerator.device
    B, ga = args.per_device_train_batch_size, args.gradient_accumulation_steps
    train_ds, val_ds = build_datasets(args, config, B * ga * world, source)
    config = prepare_actions(config, args, train_ds, val_ds)
    sampler = ResumableBatchSampler(len(train_ds), B, world, accelerator.process_index, seed=args.seed,
                                    shuffle=not args.overfit_first_batch)
    data = TrainData(train_ds, val_ds, sampler, steps_per_epoch=sampler.batches_per_epoch // ga)
    if data.steps_per_epoch == 0:
        raise TrainingError(f"{args.train_data_dir}: {len(train_ds)} training windows are too few for one "
                            f"optimizer step of {B} x {ga} (accumulation) x {world} (processes) windows")
    max_steps = (args.max_train_steps if args.max_train_steps is not None
                 else args.num_train_epochs * data.steps_per_epoch)

    model = build_model(config, args.warmstart_path).to(device)
    model.decoder.gradient_checkpointing = args.gradient_checkpointing
    # torch's fused AdamW kernel exists for CUDA and CPU (~15x faster than the per-tensor loop on CPU)
    optimizer = build_optimizer(model, args, fused=device.type in ("cuda", "cpu"))
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lr_multiplier(args.lr_scheduler_type, args.num_warmup_steps, max_steps))
    saved_with = SavedWith(recipe, decoding, resolved_recipe(config, recipe, vars(args), decoding))
    trainer = Trainer(train_config(args, data.steps_per_epoch), accelerator, model, optimizer, scheduler,
                      data.steps_per_epoch, len(train_ds), saved_with)
    trainer.begin(args.resume_from_checkpoint)
    trainer.prepare(compile_model=not args.no_compile and device.type == "cuda")
    accelerator.init_trackers("genie", config={k: v if isinstance(v, (int, float, str, bool)) else str(v)
                                               for k, v in {**vars(args), **config.to_dict(),
                                                             **recipe.to_dict()}.items()})
    try:
        train(args, accelerator, trainer, data, config, recipe, max_steps)
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
