"""Crash-safe training state: atomic checkpoint directories, safetensors + JSON serialization, RNG capture, resume.

A training checkpoint `checkpoint-<step>/` holds:
    config.json, model.safetensors   the model, as a Hugging Face checkpoint (loadable with from_pretrained)
    optimizer.safetensors/.json      optimizer tensors + the rest of its state_dict (see `flatten_state`)
    rng.safetensors/.json            RNG states of every process (torch, CUDA, numpy, python)
    trainer_state.json               step, epoch, position in the epoch, lr scheduler state, run arguments
    ema/                             the weight average (train.py --ema_decay, common/ema.py), a model directory like
                                     the checkpoint's own; only in runs that keep one
    MANIFEST.json                    size + sha256 of every file above, checked on resume (common/integrity.py)
    COMPLETE                         written last; a directory without it is never resumed from
Everything is written into a hidden temporary directory that is renamed into place once complete, so a kill at any
moment leaves either the previous set of checkpoints or the new one, never a half-written directory that looks valid.
Nothing here unpickles: tensors come from safetensors, everything else from JSON.
"""
import json
import math
import os
import random
import re
import shutil
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from common.errors import TrainingError
from common.files import COMPLETE_MARKER, TMP_PREFIX, atomic_directory, is_complete
from common.integrity import verify_manifest

CHECKPOINT_PREFIX = "checkpoint-"
FORMAT_VERSION = 1
EMA_DIR = "ema"  # a checkpoint's weight-average folder (train.py --ema_decay)
_CHECKPOINT_RE = re.compile(rf"^{CHECKPOINT_PREFIX}(\d+)$")


class TrainingStateError(TrainingError):
    """A checkpoint directory that is missing, incomplete or does not match the run (a script ends on its message,
    one line: `common.cli.run_main`)."""


# ---------------------------------------------------------------- JSON

def read_json(path, what: str):
    path = Path(path)
    if not path.is_file():
        raise TrainingStateError(f"{what}: file not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise TrainingStateError(f"{path}: {what} is not valid JSON ({e})") from None


# ---------------------------------------------------------------- nested state <-> safetensors + JSON

def flatten_state(obj, prefix: str = "t"):
    """Split a nested state (dicts, lists, tuples, tensors, numbers, strings) into a JSON skeleton and tensors.

    Tensors are replaced by {"__tensor__": key}; tuples and dicts are tagged so that non-string dict keys (the
    integer parameter ids of an optimizer state) and tuples survive the JSON round trip.
    Returns (skeleton, tensors: dict[str, Tensor]).
    """
    tensors = {}

    def walk(x, path):
        if isinstance(x, torch.Tensor):
            tensors[path] = x.detach().cpu().contiguous()
            return {"__tensor__": path}
        if isinstance(x, np.ndarray):
            return {"__ndarray__": x.tolist(), "dtype": str(x.dtype)}
        if isinstance(x, np.generic):
            return x.item()
        if isinstance(x, dict):
            return {"__dict__": [[k, walk(v, f"{path}.{i}")] for i, (k, v) in enumerate(x.items())]}
        if isinstance(x, tuple):
            return {"__tuple__": [walk(v, f"{path}.{i}") for i, v in enumerate(x)]}
        if isinstance(x, list):
            return [walk(v, f"{path}.{i}") for i, v in enumerate(x)]
        if x is None or isinstance(x, (bool, int, float, str)):
            return x
        raise TypeError(f"cannot serialize {type(x).__name__} at {path} as safetensors + JSON")

    return walk(obj, prefix), tensors


def unflatten_state(skeleton, tensors: dict, source: str = "state"):
    """Inverse of `flatten_state`."""
    def walk(x):
        if isinstance(x, list):
            return [walk(v) for v in x]
        if isinstance(x, dict):
            if "__tensor__" in x:
                if x["__tensor__"] not in tensors:
                    raise TrainingStateError(f"{source}: tensor {x['__tensor__']!r} is missing")
                return tensors[x["__tensor__"]]
            if "__ndarray__" in x:
                return np.asarray(x["__ndarray__"], dtype=x["dtype"])
            if "__tuple__" in x:
                return tuple(walk(v) for v in x["__tuple__"])
            if "__dict__" in x:
                return {k: walk(v) for k, v in x["__dict__"]}
            raise TrainingStateError(f"{source}: unexpected JSON object with keys {sorted(x)}")
        return x

    return walk(skeleton)


def save_state_files(directory, name: str, state) -> None:
    """Write `state` as `<name>.safetensors` (its tensors) + `<name>.json` (everything else)."""
    skeleton, tensors = flatten_state(state)
    save_file(tensors, str(Path(directory) / f"{name}.safetensors"))
    (Path(directory) / f"{name}.json").write_text(json.dumps(skeleton) + "\n")


def load_state_files(directory, name: str):
    directory = Path(directory)
    tensor_path = directory / f"{name}.safetensors"
    if not tensor_path.is_file():
        raise TrainingStateError(f"{directory}: missing {tensor_path.name}")
    skeleton = read_json(directory / f"{name}.json", f"{name} state")
    try:
        tensors = load_file(str(tensor_path))
    except Exception as e:  # safetensors raises its own error types for corrupt headers
        raise TrainingStateError(f"{tensor_path}: unreadable safetensors file ({e})") from None
    return unflatten_state(skeleton, tensors, source=str(tensor_path))


# ---------------------------------------------------------------- RNG states

def capture_rng_state() -> dict:
    """This process's global RNG states: python, numpy, torch CPU and (when present) every CUDA device."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict) -> None:
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    np.random.set_state(tuple(state["numpy"]))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ---------------------------------------------------------------- reproducible data order

class ResumableBatchSampler(torch.utils.data.Sampler):
    """Batches of dataset indices whose order depends only on (seed, epoch), sharded across processes.

    Epoch e permutes range(num_items) with a generator seeded by seed + e (or keeps it in order), pads it by
    wrapping around to a multiple of num_replicas, and gives process `rank` every num_replicas-th index starting at
    `rank`; these are cut into batches of batch_size (the last partial batch is dropped when drop_last, so every
    process sees the same number of full batches). `set_epoch(epoch, start_batch)` makes the next iteration start
    at batch start_batch: a resumed run skips exactly the batches it already trained on, without loading them.
    """

    def __init__(self, num_items: int, batch_size: int, num_replicas: int = 1, rank: int = 0, seed: int = 0,
                 shuffle: bool = True, drop_last: bool = True):
        if num_items < 1 or batch_size < 1 or not 0 <= rank < num_replicas:
            raise ValueError(f"ResumableBatchSampler: bad arguments num_items={num_items}, batch_size={batch_size}, "
                             f"rank={rank}, num_replicas={num_replicas}")
        self.num_items, self.batch_size = num_items, batch_size
        self.num_replicas, self.rank, self.seed = num_replicas, rank, seed
        self.shuffle, self.drop_last = shuffle, drop_last
        self.epoch, self.start_batch = 0, 0

    @property
    def items_per_replica(self) -> int:
        return math.ceil(self.num_items / self.num_replicas)

    @property
    def batches_per_epoch(self) -> int:
        if self.drop_last:
            return self.items_per_replica // self.batch_size
        return math.ceil(self.items_per_replica / self.batch_size)

    def set_epoch(self, epoch: int, start_batch: int = 0) -> None:
        self.epoch, self.start_batch = epoch, start_batch

    def epoch_indices(self, epoch: int) -> torch.Tensor:
        """This process's indices for `epoch`, in order (before batching)."""
        if self.shuffle:
            order = torch.randperm(self.num_items, generator=torch.Generator().manual_seed(self.seed + epoch))
        else:
            order = torch.arange(self.num_items)
        padded = order.repeat(math.ceil(self.items_per_replica * self.num_replicas / self.num_items))
        return padded[:self.items_per_replica * self.num_replicas][self.rank::self.num_replicas]

    def __iter__(self):
        indices = self.epoch_indices(self.epoch).tolist()
        for b in range(self.start_batch, self.batches_per_epoch):
            yield indices[b * self.batch_size:(b + 1) * self.batch_size]

    def __len__(self) -> int:
        return max(0, self.batches_per_epoch - self.start_batch)


# ---------------------------------------------------------------- training checkpoints

def checkpoint_dir(output_dir, step: int) -> Path:
    return Path(output_dir) / f"{CHECKPOINT_PREFIX}{step}"


def list_checkpoints(output_dir) -> list:
    """Complete checkpoints in `output_dir` as [(step, path)], oldest first."""
    output_dir = Path(output_dir)
    if not output_dir.is_dir():
        return []
    found = []
    for p in output_dir.iterdir():
        m = _CHECKPOINT_RE.match(p.name)
        if m and p.is_dir() and is_complete(p):
            found.append((int(m.group(1)), p))
    return sorted(found)


def resolve_resume_path(output_dir, resume_from):
    """Map --resume_from_checkpoint to a checkpoint directory: "latest" -> newest complete one (None if there is
    none yet, so a preemptible job can always pass "latest"); a path -> that directory, which must be complete."""
    if resume_from is None:
        return None
    if resume_from == "latest":
        found = list_checkpoints(output_dir)
        return found[-1][1] if found else None
    path = Path(resume_from)
    if not path.is_dir():
        raise TrainingStateError(f"--resume_from_checkpoint: no such directory: {path}")
    if not is_complete(path):
        raise TrainingStateError(f"--resume_from_checkpoint: {path} is incomplete (no {COMPLETE_MARKER} file): "
                                 f"it was being written when the run stopped; use an older checkpoint or 'latest'")
    return path


def resume_hint(output_dir) -> str:
    """One line for a run that stopped on a write error: the newest complete checkpoint and how to resume."""
    found = list_checkpoints(output_dir)
    if not found:
        return f"no complete checkpoint in {output_dir} yet"
    return f"last complete checkpoint: {found[-1][1]} (resume with --resume_from_checkpoint latest)"


def prune_checkpoints(output_dir, keep: int) -> None:
    """Delete the oldest complete checkpoints so that at most `keep` remain (keep <= 0: keep all)."""
    if keep <= 0:
        return
    for _, path in list_checkpoints(output_dir)[:-keep]:
        doomed = path.with_name(f"{TMP_PREFIX}delete-{path.name}")  # a kill mid-delete leaves no half checkpoint
        os.replace(path, doomed)
        shutil.rmtree(doomed, ignore_errors=True)


def save_training_checkpoint(ckpt_dir, model, optimizer, trainer_state: dict, rng_states: list,
                             model_kwargs: Optional[dict] = None, extra_models: Optional[dict] = None) -> None:
    """Atomically write a full training checkpoint. `model` must have `save_pretrained(dir, **model_kwargs)`;
    `trainer_state` is JSON-serializable (step, epoch, scheduler state, ...); `rng_states` holds one
    `capture_rng_state()` per process; `extra_models` {folder name: model} are saved the same way in subfolders
    (EMA_DIR: the weight average)."""
    with atomic_directory(ckpt_dir, "the training checkpoint") as tmp:
        model.save_pretrained(tmp, **(model_kwargs or {}))
        for name, extra in (extra_models or {}).items():
            extra.save_pretrained(tmp / name, **(model_kwargs or {}))
        save_state_files(tmp, "optimizer", optimizer.state_dict())
        save_state_files(tmp, "rng", rng_states)
        (tmp / "trainer_state.json").write_text(
            json.dumps({"format_version": FORMAT_VERSION, **trainer_state}, indent=2, sort_keys=True) + "\n")


def load_training_checkpoint(ckpt_dir) -> dict:
    """Read a checkpoint written by `save_training_checkpoint`.

    Returns {"model_path": Path, "config": dict, "optimizer": state_dict, "rng": list, "trainer": dict}; load the
    weights with `safetensors.torch.load_model(model, model_path)` (it restores shared tensors too).
    """
    ckpt_dir = Path(ckpt_dir)
    if not is_complete(ckpt_dir):
        raise TrainingStateError(f"{ckpt_dir}: incomplete checkpoint (no {COMPLETE_MARKER} file)")
    verify_manifest(ckpt_dir)  # IntegrityError naming the file when a byte changed since it was written
    trainer = read_json(ckpt_dir / "trainer_state.json", "trainer state")
    if trainer.get("format_version") != FORMAT_VERSION:
        raise TrainingStateError(f"{ckpt_dir / 'trainer_state.json'}: format_version "
                                 f"{trainer.get('format_version')!r}, this code reads version {FORMAT_VERSION}")
    model_path = ckpt_dir / "model.safetensors"
    if not model_path.is_file():
        raise TrainingStateError(f"{ckpt_dir}: missing model.safetensors")
    return {
        "model_path": model_path,
        "config": read_json(ckpt_dir / "config.json", "model config"),
        "optimizer": load_state_files(ckpt_dir, "optimizer"),
        "rng": load_state_files(ckpt_dir, "rng"),
        "trainer": trainer,
    }
