"""Diagnostics of a dynamics model's futures, scored like evaluate.py's protocols (evaluation/protocols.py); diagnose.py
is their command line (`python diagnose.py SUBCOMMAND --help`).

copy ceiling: the rollout protocol's scores of the best futures made only of copies of the frame before's nearby
tokens, chosen knowing the true frames (evaluation/copy_ceiling.py). per-window: the rollout protocol, also writing
each window's own scores. withheld actions: the protocols on an action model given none. control: does the model
turn and walk as its buttons say (evaluation/control_check.py).
"""
import logging
import sys
from dataclasses import dataclass, field
from typing import Any, Dict, Optional

import torch
from tqdm import tqdm

from common.errors import DataMismatchError
from evaluation.copy_ceiling import ceiling_rollout
from evaluation.protocols import (EvalConfig, EvaluationError, add_rollout_scores, apply_decoding, frame_scorer,
                                  load_model, model_windows, rollout_evaluate, rollout_result, start_process,
                                  teacher_forced_run, windows_dataset, windows_loader, write_per_window)

logger = logging.getLogger("evaluation.diagnostics")


# ------------------------------------------------------------------ copy ceiling
@torch.no_grad()
def copy_ceiling_evaluate(loader, cfg: EvalConfig, device: torch.device, scorer, num_bits: int, radius: int,
                          block: int, per_window=None) -> dict:
    """The copy ceiling's JSON line over `loader`: the rollout protocol's scores of
    evaluation.copy_ceiling.ceiling_rollout's frames (copies from at most `radius` positions away, one displacement
    per block x block tile; each window's own scores appended to `per_window` when a list)."""
    P, with_lpips = cfg.num_prompt_frames, not cfg.skip_lpips
    sums, num_examples, exact, num_tokens = {}, 0, 0, 0
    for batch in _progress(loader, "copy ceiling"):
        x_BTHW = batch["tokens"].to(device).long()
        tokens_BTHW, exact_B = ceiling_rollout(x_BTHW, P, radius, block, num_bits)
        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window)
        num_examples += x_BTHW.shape[0]
        exact += int(exact_B.sum())
        num_tokens += tokens_BTHW[:, P:].numel()
    result = rollout_result(sums, num_examples, P, None)
    return {**result, "protocol": "copy_ceiling", "radius": radius, "block": block,
            "exact_share": exact / max(num_tokens, 1)}


def _progress(loader, desc: str):
    return tqdm(loader, desc=desc, unit="batch", file=sys.stderr)


def run_copy_ceiling(cfg: EvalConfig, radius: int, block: int, per_window_out: Optional[str] = None) -> dict:
    """The copy ceiling of cfg's windows (no checkpoint is read); each window's scores to per_window_out if set."""
    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    dataset = windows_dataset(cfg)
    h, w = dataset.metadata["h"], dataset.metadata["w"]
    if h % block or w % block:
        raise EvaluationError(f"--ceiling_block {block} does not divide the {h} x {w} token frames of "
                              f"{cfg.val_data_dir}")
    indices, loader = windows_loader(dataset, cfg)
    logger.info("copy ceiling of %d windows of %s (radius %d, block %d)", len(indices), cfg.val_data_dir, radius,
                block)
    num_bits = (int(dataset.metadata["vocab_size"]) - 1).bit_length()
    per_window = [] if per_window_out else None
    scorer = frame_scorer(cfg, dataset, device, "copy_ceiling")
    result = copy_ceiling_evaluate(loader, cfg, device, scorer, num_bits, radius, block, per_window)
    if per_window is not None:
        write_per_window(per_window_out, per_window, dataset, indices)
    return result


# ------------------------------------------------------------------ per window
def rollout_writing_windows(model, cfg: EvalConfig, device: torch.device, per_window_out: Optional[str] = None,
                            withhold_actions: bool = False) -> dict:
    """The rollout protocol's JSON line for `model`, with each window's own scores written to per_window_out when
    it is set."""
    dataset, indices, loader = model_windows(model, cfg, withhold_actions=withhold_actions)
    per_window = [] if per_window_out else None
    result = rollout_evaluate(model, loader, cfg, device, frame_scorer(cfg, dataset, device, "rollout"),
                              per_window, withhold_actions=withhold_actions)
    if per_window is not None:
        write_per_window(per_window_out, per_window, dataset, indices)
    return result


def run_per_window(cfg: EvalConfig, per_window_out: str) -> dict:
    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    return rollout_writing_windows(load_model(cfg, device), cfg, device, per_window_out)


# ------------------------------------------------------------------ withheld actions
def run_withheld_actions(cfg: EvalConfig, protocol: str, per_window_out: Optional[str] = None) -> dict:
    """evaluate.py's `protocol` ("teacher_forced" or "rollout") on an action model given no actions."""
    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    model = load_model(cfg, device, teacher_forced_protocol=protocol == "teacher_forced")
    if not model.config.uses_actions:
        raise DataMismatchError(f"withheld_actions: the checkpoint {cfg.checkpoint_dir} takes no actions to "
                                f"withhold (evaluate.py scores it as it is)")
    if protocol == "rollout":
        result = rollout_writing_windows(model, cfg, device, per_window_out, withhold_actions=True)
    else:
        dataset, _, loader = model_windows(model, cfg, withhold_actions=True)
        with torch.no_grad():
            result, _ = teacher_forced_run(model, loader, dataset, cfg, device, withhold_actions=True)
    return {**result, "actions_withheld": True}


# ------------------------------------------------------------------ control
@dataclass
class ControlConfig:
    """The control check: num_starts windows spread over val_data_dir, each control (every button, and none) held
    for `steps` steps, the sampler seeded with `seed`; the model of checkpoint_dir decoding as its checkpoint says,
    overridden by `decoding` (DecodingConfig fields); the real world beside it unless real_world is False. Forward
    motion is measured by the motion estimator at motion_estimator (the one the policies protocol trains into its
    policy folder) when that file exists, else by the zoom between frames."""
    checkpoint_dir: str = "data/genie_model/final_checkpt"
    val_data_dir: str = "data/unseen/val"
    tokenizer_ckpt: Optional[str] = None
    num_starts: int = 24
    steps: int = 8
    seed: int = 0
    decoding: Dict[str, Any] = field(default_factory=dict)
    real_world: bool = True
    num_threads: int = 0
    motion_estimator: str = "data/policies/motion_estimator.safetensors"


def run_control(cfg: ControlConfig) -> dict:
    from envs.pairing import real_world_for
    from envs.world_model import WorldModelEnv
    from pathlib import Path

    from evaluation.control_check import control_check, summary_lines
    from evaluation.protocols import example_indices
    from sample_world.motion_estimator import load_motion_estimator

    start_process("cpu", cfg.num_threads, cfg.seed)
    env = WorldModelEnv.from_checkpoint(cfg.checkpoint_dir, cfg.val_data_dir, cfg.tokenizer_ckpt, device="cpu")
    apply_decoding(env.model, cfg.decoding, cfg.checkpoint_dir)
    if not env.buttons:
        raise DataMismatchError(f"control: the checkpoint {cfg.checkpoint_dir} is not driven by the sample world's "
                                f"buttons (its action_names are {env.model.config.action_names})")
    real_env, raw_npz = real_world_for(env, cfg.val_data_dir) if cfg.real_world else (None, None)
    if real_env is None:
        logger.info("no real world to compare with: %s", raw_npz)
    estimator = None
    if Path(cfg.motion_estimator).is_file():
        estimator = load_motion_estimator(cfg.motion_estimator)
        logger.info("forward motion: the motion estimator %s (map units per step)", cfg.motion_estimator)
    else:
        logger.info("forward motion: the zoom between frames (%s not found; ./evaluate.py --protocol policies "
                    "trains it)", cfg.motion_estimator)
    starts = example_indices(len(env.starts), cfg.num_starts, spread=True)
    result = control_check(env, starts, cfg.steps, cfg.seed, real_env, raw_npz if real_env else None,
                           estimator=estimator)
    unit = "map units" if estimator is not None else "zoom %"
    for world in ("model", "real"):
        if result[world] is not None:
            for line in summary_lines(world, result[world], unit):
                logger.info(line)
    return {"checkpoint_dir": str(cfg.checkpoint_dir), "val_data_dir": str(cfg.val_data_dir),
            "temperature": env.model.decoding.temperature, "seed": cfg.seed, "decoding": env.model.decoding.to_dict(),
            "motion_estimator": str(cfg.motion_estimator) if estimator is not None else None, **result}
