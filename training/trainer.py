"""The training state around train.py's loop: step counter, guarded optimizer step, weight average, checkpoints.

train.py builds the model, optimizer, schedule and data, then calls, per optimizer step, its own forward/backward
and `Trainer.optimizer_step`. The Trainer keeps what a resumed run must find again (common/train_state.py writes it
atomically to `output_dir/checkpoint-<step>/`): the weights, the optimizer and schedule states, every process's RNG
state, the step, the data position and the weight average. A run resumed from a checkpoint takes exactly the steps
the uninterrupted run would have taken, as long as the data order (seed, dataset, batch size, process count) is
the same.
"""
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import torch
from accelerate import Accelerator
from accelerate.utils import gather_object
from safetensors.torch import load_model

from common.ema import WeightAverage
from common.train_state import (EMA_DIR, TrainingStateError, atomic_directory, capture_rng_state, checkpoint_dir,
                                list_checkpoints, load_training_checkpoint, prune_checkpoints, resolve_resume_path,
                                restore_rng_state, save_training_checkpoint)
from genie.config import TrainingRecipe
from genie.decoding import DecodingConfig
from training.guards import DivergenceGuard, NonfiniteGuard

logger = logging.getLogger("train")


@dataclass(frozen=True)
class TrainConfig:
    """The Trainer's settings, from train.py's flags of the same names.

    checkpoint_every: optimizer steps between checkpoints (0: never). max_grad_norm <= 0: no clipping.
    ema_decay 0: no weight average. flags: every train.py flag's value, kept in each checkpoint's trainer state.
    """
    output_dir: str
    seed: int
    optimizer: str
    per_device_train_batch_size: int
    gradient_accumulation_steps: int
    max_grad_norm: float
    max_nonfinite_steps: int
    max_diverged_steps: int
    checkpoint_every: int
    checkpoints_total_limit: int
    ema_decay: float
    flags: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SavedWith:
    """What every saved model carries besides its weights: the masking recipe (config.json), the decoding
    (decoding.json) and the resolved run recipe (recipe.json; None: none written)."""
    recipe: TrainingRecipe
    decoding: DecodingConfig = field(default_factory=DecodingConfig)
    run_recipe: Optional[dict] = None


class Trainer:
    """One process's training state. All processes call every method (the RNG states are gathered and the step's
    flags agreed on); only the main process writes files.

    model and optimizer are the plain module and optimizer (what checkpoints save); `prepare` wraps them for the
    loop (`ddp_model`, `ddp_optimizer`). steps_per_epoch and num_train_windows describe the data order, which a
    resumed run checks against its checkpoint.
    """

    def __init__(self, cfg: TrainConfig, accelerator: Accelerator, model, optimizer: torch.optim.Optimizer,
                 scheduler, steps_per_epoch: int, num_train_windows: int, saved_with: SavedWith):
        self.cfg, self.accelerator = cfg, accelerator
        self.model, self.optimizer, self.scheduler = model, optimizer, scheduler
        self.ddp_model, self.ddp_optimizer = model, optimizer
        self.steps_per_epoch, self.num_train_windows = steps_per_epoch, num_train_windows
        self.saved_with = saved_with
        self.device = accelerator.device
        self.rank, self.world = accelerator.process_index, accelerator.num_processes
        self.step = 0  # optimizer steps taken, skipped ones included
        self.last_saved_step: Optional[int] = None
        self.ema: Optional[WeightAverage] = None
        self.nonfinite = NonfiniteGuard(cfg.max_nonfinite_steps)
        self.divergence = DivergenceGuard(cfg.max_diverged_steps, model.config.image_vocab_size)

    # ---- start
    def begin(self, resume_from: Optional[str]) -> None:
        """Resume from `resume_from` ('latest', a checkpoint directory, or None: a fresh run) and start the weight
        average (--ema_decay), continuing the checkpoint's own when it has one."""
        resumed = self._resume(resume_from)
        if self.cfg.ema_decay > 0:
            self.ema = self._weight_average(resumed)

    def prepare(self, compile_model: bool) -> None:
        """Wrap the model and optimizer for the loop (DDP across processes; torch.compile'd when asked)."""
        self.ddp_model, self.ddp_optimizer = self.accelerator.prepare(self.model, self.optimizer)
        if compile_model:
            self.ddp_model = torch.compile(self.ddp_model)

    def _resume(self, resume_from: Optional[str]) -> Optional[Tuple[Path, dict]]:
        """Load the checkpoint's training state; returns (its path, its trainer state), or None."""
        output_dir = self.cfg.output_dir
        path = resolve_resume_path(output_dir, resume_from)
        if path is None:
            if resume_from == "latest":
                logger.info("no complete checkpoint in %s yet: starting from scratch", output_dir)
            return None
        ckpt = load_training_checkpoint(path)
        self._check_same_run(path, ckpt)
        state = ckpt["trainer"]
        load_model(self.model, str(ckpt["model_path"]), device=str(self.device))
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step = self.last_saved_step = state["step"]
        if not self._same_data_order(state):
            logger.warning("resuming with a different seed, dataset, batch size or process count than %s: training "
                           "continues from step %d but the data order differs from the interrupted run", path,
                           self.step)
        rng = ckpt["rng"]
        restore_rng_state(rng[self.rank] if len(rng) == self.world else rng[0])
        logger.info("resumed from %s at step %d (epoch %d)", path, self.step, state["epoch"])
        return path, state

    def _check_same_run(self, path: Path, ckpt: dict) -> None:
        """The checkpoint must hold this model and this optimizer's state."""
        differing = sorted(k for k, v in self.model.config.to_dict().items() if ckpt["config"].get(k) != v)
        if differing:
            raise TrainingStateError(f"{path / 'config.json'}: the checkpoint's model config differs from "
                                     f"--genie_config in {differing}")
        saved = ckpt["trainer"].get("args", {}).get("optimizer", "adamw")  # runs from before --optimizer: AdamW
        if saved != self.cfg.optimizer:
            raise TrainingStateError(f"{path}: the run was trained with --optimizer {saved}, not "
                                     f"{self.cfg.optimizer}; resume it with the same optimizer")

    def _same_data_order(self, state: dict) -> bool:
        return all(state.get(k) == v for k, v in self._data_order().items())

    def _data_order(self) -> dict:
        """What decides the order of the training windows (ResumableBatchSampler)."""
        return {"world_size": self.world, "seed": self.cfg.seed, "num_train_windows": self.num_train_windows,
                "per_device_train_batch_size": self.cfg.per_device_train_batch_size,
                "gradient_accumulation_steps": self.cfg.gradient_accumulation_steps}

    def _weight_average(self, resumed: Optional[Tuple[Path, dict]]) -> WeightAverage:
        average = WeightAverage(self.model, self.cfg.ema_decay)
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

    # ---- one optimizer step
    def optimizer_step(self, loss: torch.Tensor, stop_requested: bool) -> Tuple[float, float, bool]:
        """After the backward passes of one step (loss: their mean, a 0-d tensor): clip the gradients, then step the
        optimizer unless the loss or gradient is NaN/inf on any process, move the weight average and the schedule,
        and count the step. Returns (loss, gradient norm, whether any process got SIGTERM).

        Raises TrainingError when the guards stop the run: too many NaN/inf steps in a row (after saving a
        checkpoint of the last good weights) or a diverged loss (saving nothing)."""
        max_norm = self.cfg.max_grad_norm if self.cfg.max_grad_norm > 0 else float("inf")
        grad_norm = self.accelerator.clip_grad_norm_(self.ddp_model.parameters(), max_norm)
        finite, stop, diverged = self._agreed_flags(loss, grad_norm, stop_requested)
        if finite:
            self.ddp_optimizer.step()
            if self.ema is not None:
                self.ema.update(self.model)
        self.ddp_optimizer.zero_grad(set_to_none=True)
        self.scheduler.step()  # the schedule follows the data position, skipped steps included
        self.step += 1
        loss_value = loss.item()
        if self.nonfinite.check(finite, self.step, loss_value):
            self.save_checkpoint()
            raise self.nonfinite.error(checkpoint_dir(self.cfg.output_dir, self.step))
        if finite and self.divergence.check(diverged):
            raise self.divergence.error(self.step, loss_value, list_checkpoints(self.cfg.output_dir))
        return loss_value, float(grad_norm), stop

    def _agreed_flags(self, loss: torch.Tensor, grad_norm: torch.Tensor, stop_requested: bool):
        """(finite, stop, diverged), each agreed on by all processes so that they all skip or stop together."""
        flags = torch.stack([(~torch.isfinite(loss)) | (~torch.isfinite(grad_norm)),
                             torch.tensor(stop_requested, device=self.device),
                             loss > self.divergence.threshold]).float()
        if self.world > 1:
            flags = self.accelerator.reduce(flags, reduction="sum")
        return bool(flags[0] == 0), bool(flags[1] > 0), bool(flags[2] > 0)

    @property
    def lr(self) -> float:
        return self.scheduler.get_last_lr()[0]

    # ---- checkpoints
    def checkpoint_due(self) -> bool:
        return self.cfg.checkpoint_every > 0 and self.step % self.cfg.checkpoint_every == 0

    def trainer_state(self) -> dict:
        """trainer_state.json: where the run is, and what a resume checks."""
        epoch, batch = divmod(self.step, self.steps_per_epoch)
        return {"step": self.step, "epoch": epoch, "batch_in_epoch": batch * self.cfg.gradient_accumulation_steps,
                "steps_per_epoch": self.steps_per_epoch, "scheduler": self.scheduler.state_dict(),
                **self._data_order(), "args": dict(self.cfg.flags),
                **({"ema_updates": self.ema.updates} if self.ema else {})}

    def save_checkpoint(self) -> None:
        """checkpoint-<step>/: the full training state, written atomically; older ones pruned after."""
        rng_states = gather_object([capture_rng_state()]) if self.world > 1 else [capture_rng_state()]
        if self.accelerator.is_main_process:
            path = checkpoint_dir(self.cfg.output_dir, self.step)
            extra = {EMA_DIR: self.ema.model} if self.ema else {}
            save_training_checkpoint(path, self.model, self.optimizer, self.trainer_state(), rng_states,
                                     model_kwargs=self._model_kwargs(), extra_models=extra or None)
            prune_checkpoints(self.cfg.output_dir, self.cfg.checkpoints_total_limit)
            logger.info("saved training state to %s", path)
        self.last_saved_step = self.step
        self.accelerator.wait_for_everyone()

    def save_if_unsaved(self) -> None:
        """A checkpoint of this step unless one was just written."""
        if self.last_saved_step != self.step:
            self.save_checkpoint()

    def final_model(self):
        """What final_checkpt gets and validation scores: the weight average, or the plain module (no DDP hooks,
        no recompilation for eval mode)."""
        return self.ema.model if self.ema else self.model

    def save_final(self) -> None:
        """final_checkpt/: the model alone (the weight average when there is one), written atomically."""
        if self.accelerator.is_main_process:
            path = Path(self.cfg.output_dir) / "final_checkpt"
            model = self.final_model()
            with atomic_directory(path, "the final model") as tmp:
                model.save_pretrained(tmp, **self._model_kwargs())
            if self.ema:
                logger.info("saved the weight average of %d steps (--ema_decay %g) to %s; the last step's own "
                            "weights are in the newest checkpoint-<step>/ when checkpointing is on",
                            self.ema.updates, self.ema.decay, path)
            else:
                logger.info("saved the final model to %s", path)
        self.accelerator.wait_for_everyone()

    def _model_kwargs(self) -> dict:
        # the decoding goes to decoding.json, never onto the model: the copy head would add copy_bias in training
        return {"recipe": self.saved_with.recipe, "run_recipe": self.saved_with.run_recipe,
                "decoding": self.saved_with.decoding}
