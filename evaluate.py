#!/usr/bin/env python
"""The 1X challenge evaluator (docs/formats.md §5): two protocols over the validation windows (16 frames at stride
15, non-overlapping), one JSON line on stdout (the last line; progress goes to stderr), one process on one device.

    ./evaluate.py --val_data_dir data/val_v1.1 --checkpoint_dir 1x-technologies/GENIE_35M
    ./evaluate.py --protocol rollout --num_prompt_frames 8 --max_examples 48 --spread_examples

Teacher-forced (the default): each frame t = 1..T-1 is predicted with MaskGIT from the ground-truth frames before
it. Keys: loss (factored CE), acc (token accuracy), copy_acc (the accuracy of copying frame t-1: the baseline acc
must beat), pred_lpips (null with --skip_lpips), gen_time, dec_time (s per frame; null when nothing is decoded),
num_examples. Action-conditioned checkpoints see the actions of frames < t only. Latent-action checkpoints add
delta_psnr (PSNR of futures generated with the inferred latent actions minus with random ones; null with
--skip_lpips; the mean over --delta_psnr_seeds sampler seeds, each in delta_psnr_runs) and action_probe_acc,
action_majority_rate (lam/probe.py's probe of the latent ids against actions/buttons.bin, fitted on
--train_data_dir; null when a split lacks the files).

Rollout (--protocol rollout, the sampling challenge): each window's first --num_prompt_frames P frames prompt, the
other T - P are generated free-running (action models play the window's own action rows), decoded, and scored per
horizon against the true frames, next to "hold", repeating the last prompt frame. Keys: protocol, num_prompt_frames;
rollout_psnr, hold_psnr, rollout_ssim, hold_ssim, rollout_lpips, hold_lpips (lists over horizons; LPIPS null with
--skip_lpips); rollout_unchanged, true_unchanged (the share of tokens equal to the same position one frame earlier)
and rollout_repeated, true_repeated (equal to their left neighbour): a rollout that freezes or flattens; each list
with its _mean; where the dataset is a sample world split with its raw frames beside it, the same scores against
the real frames instead of the decoded true tokens: rollout_real_*, hold_real_* (holding the last real prompt frame)
and tokenizer_real_* (the tokenizer's reconstruction of the true frames, the ceiling of any model that speaks its
tokens), each * in psnr, ssim, lpips; rollout_far_psnr, hold_far_psnr (the last horizon); the sampler (maskgit_steps, temperature,
unmask_mode, copy_bias, greedy_tokens, stall_ratio); gen_time (s per generated frame); num_examples.

Play (--protocol play, evaluation/play_protocol.py): what a player sees, over a minute of play. From starts spread
over a sample world split's recorded walks, the model gets --num_prompt_frames real frames and replays the walk's
buttons for --play_steps steps (default 64, 27 s), its context running over its own frames; each step is scored
against the real frame (not its tokens) by PSNR, LPIPS, sharpness and, per horizon bin, KID, beside the tokenizer's
own reconstruction (the ceiling) and holding the last real frame. Keys: protocol, data_dir, steps, prompt_frames,
num_starts, decoding, per_step and per_bin ({model, tokenizer, hold} x {psnr, lpips, sharpness, kid_x1000}).

Decoding: a model samples as its checkpoint's decoding.json says (what it was trained to be sampled with; the
published checkpoints have none and decode as the published code: greedy, 2 MaskGIT steps); each decoding flag
overrides one value, and the JSON line records what was used (the teacher-forced protocol under "decoding": the
checkpoint's MaskGIT steps, greedy, no copy bias, as the challenge scores a model, unless flags say otherwise).

Diagnostics that score other futures the same way (the copy ceiling, per-window scores and their breakdown by
motion, a model without its actions, the control check, the data's baselines) are `diagnose.py`.
"""
import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch

from common.cli import run_main, setup_logging
from common.shutdown import exit_on_sigterm
from data import RawTokenDataset
from training.action_streams import LATENT_ACTION_NAME, latent_action_sidecar
from evaluation.cli import (PLAY_HELP, POLICIES_HELP, add_play_args, add_policy_args, add_protocol_args,
                            add_save_outputs_arg, add_window_args, check_policy_args, check_protocol_args,
                            check_window_args, eval_config, play_config, policy_config)
from evaluation.play_protocol import bin_lines, run_play
from evaluation.policy_ranking import run_policies
from evaluation.protocols import (EvalConfig, EvaluationError, delta_psnr, frame_scorer, load_model,  # noqa: F401
                                  model_windows, real_frames_of, rollout_evaluate, start_process,
                                  teacher_forced_run)
from genie.model import STMaskGIT
from lam.data import valid_targets
from lam.probe import action_probe, transition_labels

logger = logging.getLogger("evaluate")

DEFAULT_TRAIN_DIR = "data/sample/train"
BUTTONS_NAME = "buttons"  # the sample world's true actions, labels of the latent action probe


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="evaluate.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_protocol_args(parser, ("policies", "play"), POLICIES_HELP + PLAY_HELP)
    add_window_args(parser)
    add_save_outputs_arg(parser)
    parser.add_argument("--delta_psnr_seeds", type=int, default=1,
                        help="Teacher-forced protocol, latent-action checkpoints: compute delta_psnr with this many "
                             "sampler seeds (--seed, --seed + 1, ...; each run exactly what that --seed alone gives) "
                             "and report the mean (delta_psnr) and every run (delta_psnr_runs). One draw of the noise "
                             "moves it by tenths of a dB on a few dozen windows (default: %(default)s).")
    parser.add_argument("--train_data_dir", default=DEFAULT_TRAIN_DIR,
                        help="Teacher-forced protocol, latent-action checkpoints: the token dataset whose latent "
                             "actions and buttons fit the latent action probe (default: %(default)s).")
    add_policy_args(parser)
    add_play_args(parser)
    args = parser.parse_args(argv)
    check_window_args(parser, args)
    check_policy_args(parser, args)
    if args.delta_psnr_seeds < 1:
        parser.error(f"--delta_psnr_seeds must be >= 1, got {args.delta_psnr_seeds}")
    check_protocol_args(parser, args)
    return args


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


def teacher_forced_result(model: STMaskGIT, loader, dataset: RawTokenDataset, cfg: EvalConfig, device: torch.device,
                          train_data_dir: str, delta_psnr_seeds: int) -> dict:
    """The teacher-forced protocol's metrics, plus the latent-action metrics for models that have them."""
    with torch.no_grad():
        result, scorer = teacher_forced_run(model, loader, dataset, cfg, device)
        if model.config.num_latent_actions:
            if scorer is None:
                logger.warning("--skip_lpips: nothing is decoded, so delta_psnr is null")
            seeds = [cfg.seed + i for i in range(delta_psnr_seeds)]
            runs = None if scorer is None else delta_psnr(model, loader, cfg, device, scorer, seeds)
            result["delta_psnr"] = None if runs is None else sum(runs) / len(runs)
            result["delta_psnr_runs"] = runs
            result.update(latent_action_probe(dataset, train_data_dir, cfg.stride))
    return result


def run(args: argparse.Namespace) -> dict:
    """The JSON line of --protocol on --checkpoint_dir and --val_data_dir."""
    if args.protocol == "policies":
        return run_policies(policy_config(args))
    if args.protocol == "play":
        result = run_play(play_config(args))
        for line in bin_lines(result):
            logger.info(line)
        return result
    cfg = eval_config(args)
    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    model = load_model(cfg, device, teacher_forced_protocol=args.protocol == "teacher_forced")
    dataset, indices, loader = model_windows(model, cfg)
    if args.protocol == "rollout":
        return rollout_evaluate(model, loader, cfg, device, frame_scorer(cfg, dataset, device, "rollout"),
                                real=real_frames_of(dataset, indices, cfg.stride))
    return teacher_forced_result(model, loader, dataset, cfg, device, args.train_data_dir, args.delta_psnr_seeds)


def main(argv=None) -> int:
    setup_logging()
    exit_on_sigterm()  # the policies protocol starts ViZDoom engines: SIGTERM closes them, as Ctrl-C does
    print(json.dumps(run(parse_args(argv))))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("evaluate.py", main))
