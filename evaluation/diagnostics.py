"""Diagnostics of a dynamics model's futures, scored like evaluate.py's protocols (evaluation/protocols.py): one
subcommand each (`python -m evaluation.diagnostics SUBCOMMAND --help` explains it and its flags), one JSON line on stdout
(the last line; progress goes to stderr).

    python -m evaluation.diagnostics copy_ceiling --ceiling_block 8 --max_examples 48 --spread_examples
    python -m evaluation.diagnostics per_window --per_window_out windows.jsonl --max_examples 48 --spread_examples
    python -m evaluation.diagnostics breakdown windows.jsonl --val_data_dir data/sample/val --column 1
    python -m evaluation.diagnostics withheld_actions --protocol rollout --max_examples 48
    python -m evaluation.diagnostics control --val_data_dir data/unseen/val --num_starts 24
"""
import argparse
import functools
import json
import logging
import sys

import torch
from tqdm import tqdm

from common.cli import run_main, setup_logging
from common.errors import DataMismatchError
from evaluation.copy_ceiling import ceiling_rollout
from evaluation.protocols import (EvaluationError, add_per_window_arg, add_prompt_arg, add_protocol_args,
                              add_save_outputs_arg, add_window_args, add_rollout_scores, check_per_window_arg,
                              check_prompt_arg, check_protocol_args, check_window_args, frame_scorer, load_model,
                              model_windows, rollout_evaluate, rollout_result, start_process, teacher_forced_run,
                              windows_dataset, windows_loader, write_per_window)
from evaluation.rollout_breakdown import breakdown, describe

logger = logging.getLogger("evaluation.diagnostics")

PROG = "python -m evaluation.diagnostics"

COPY_CEILING_DOC = """\
The rollout protocol's windows, prompt and scores, with the generated frames replaced by the best futures made
only of whole-token copies, chosen knowing the true frames (evaluation/copy_ceiling.py); no checkpoint is read. Each
token is copied from a neighbour within --ceiling_radius positions in the ceiling's own frame before, one
displacement per --ceiling_block x --ceiling_block tile of positions: how good the previous-frame pointer's copies
could be. The JSON line has the rollout protocol's keys (protocol "copy_ceiling"; rollout_* are the ceiling's
frames; gen_time null) without the sampler's, plus radius, block and exact_share (the share of the ceiling's tokens
that are the true ones)."""

PER_WINDOW_DOC = """\
evaluate.py's rollout protocol (the same flags and JSON line) that also writes each window's own per-horizon
lists to --per_window_out, one JSON line per window with where it lies in the dataset (window, first_frame,
segment_id), so that the scores can be split by what happens in each window (its actions, its map; `breakdown`)."""

BREAKDOWN_DOC = """\
A --per_window_out file's windows cut into --bins groups of equal size by one number: the mean absolute value of
one action column over the window's generated frames (each row the mean over its window step; the sample world's
measured_motion column 1 is the turn rate, column 0 the forward speed, as measured). Each group's futures are compared with
holding the last prompt frame per horizon (evaluation/rollout_breakdown.py): a mean over all windows can hide a group of
windows where the futures lose to holding; this shows which motion it is. One readable line per group goes to
stderr; the JSON line is {"stream", "column", "groups": [{"low", "high", "num_windows", "psnr_gain" (dB per
horizon), "psnr_gain_mean", "lpips_rollout", "lpips_hold" (null when the file has no LPIPS)}, ...]}."""

WITHHELD_ACTIONS_DOC = """\
evaluate.py's protocols (the same flags) on a model with action inputs that is given none: every frame gets the
learned "no action" input that training's action dropout teaches, to measure what the model predicts from the
frames alone; the dataset needs no action streams. The JSON line is the protocol's, without the latent-action
metrics (delta_psnr, the probe), plus "actions_withheld": true."""


# ------------------------------------------------------------------ copy_ceiling
@torch.no_grad()
def copy_ceiling_evaluate(loader, args: argparse.Namespace, device: torch.device, scorer, num_bits: int,
                          per_window=None) -> dict:
    """The copy ceiling's JSON line over `loader` (module doc): the rollout protocol's scores of
    evaluation.copy_ceiling.ceiling_rollout's frames (each window's own appended to `per_window` when a list)."""
    P, with_lpips = args.num_prompt_frames, not args.skip_lpips
    sums, num_examples, exact, num_tokens = {}, 0, 0, 0
    for batch in _progress(loader, "copy ceiling"):
        x_BTHW = batch["tokens"].to(device).long()
        tokens_BTHW, exact_B = ceiling_rollout(x_BTHW, P, args.ceiling_radius, args.ceiling_block, num_bits)
        add_rollout_scores(sums, scorer, tokens_BTHW, x_BTHW, P, with_lpips, per_window)
        num_examples += x_BTHW.shape[0]
        exact += int(exact_B.sum())
        num_tokens += tokens_BTHW[:, P:].numel()
    result = rollout_result(sums, num_examples, P, None)
    return {**result, "protocol": "copy_ceiling", "radius": args.ceiling_radius, "block": args.ceiling_block,
            "exact_share": exact / max(num_tokens, 1)}


def _progress(loader, desc: str):
    return tqdm(loader, desc=desc, unit="batch", file=sys.stderr)


def run_copy_ceiling(args: argparse.Namespace) -> dict:
    device = start_process(args)
    dataset = windows_dataset(args)
    h, w = dataset.metadata["h"], dataset.metadata["w"]
    if h % args.ceiling_block or w % args.ceiling_block:
        raise EvaluationError(f"--ceiling_block {args.ceiling_block} does not divide the {h} x {w} token frames of "
                              f"{args.val_data_dir}")
    indices, loader = windows_loader(dataset, args)
    logger.info("copy ceiling of %d windows of %s (radius %d, block %d)", len(indices), args.val_data_dir,
                args.ceiling_radius, args.ceiling_block)
    num_bits = (int(dataset.metadata["vocab_size"]) - 1).bit_length()
    per_window = [] if args.per_window_out else None
    scorer = frame_scorer(args, dataset, device, "copy_ceiling")
    result = copy_ceiling_evaluate(loader, args, device, scorer, num_bits, per_window)
    if per_window is not None:
        write_per_window(args.per_window_out, per_window, dataset, indices)
    return result


def add_copy_ceiling_parser(subparsers) -> None:
    parser = _subparser(subparsers, "copy_ceiling", "the rollout protocol's scores of the best futures made only of "
                                                    "copies of the frame before's nearby tokens (no checkpoint)",
                        COPY_CEILING_DOC)
    add_window_args(parser, checkpoint=False)
    add_prompt_arg(parser)
    parser.add_argument("--ceiling_radius", type=int, default=2,
                        help="Copies come from neighbours at most this many positions away in each direction, >= 0 "
                             "(default: %(default)s; a pointer's copy_radius; 0 holds the last prompt frame).")
    parser.add_argument("--ceiling_block", type=int, default=1,
                        help="Positions in each block x block tile share one displacement, >= 1 (default: "
                             "%(default)s: every position its own; the frame's side: one shift of the whole frame). "
                             "Must divide the frame's height and width in tokens.")
    add_per_window_arg(parser, "Also ")
    parser.set_defaults(check=functools.partial(check_copy_ceiling, parser), run=run_copy_ceiling)


def check_copy_ceiling(parser, args: argparse.Namespace) -> None:
    check_window_args(parser, args)
    if args.ceiling_radius < 0 or args.ceiling_block < 1:
        parser.error(f"--ceiling_radius must be >= 0 and --ceiling_block >= 1, got {args.ceiling_radius} and "
                     f"{args.ceiling_block}")
    check_prompt_arg(parser, args)
    check_per_window_arg(parser, args)


# ------------------------------------------------------------------ per_window
def rollout_writing_windows(model, args: argparse.Namespace, device: torch.device,
                            withhold_actions: bool = False) -> dict:
    """The rollout protocol's JSON line for `model`, with each window's own scores written to --per_window_out when
    it is set."""
    dataset, indices, loader = model_windows(model, args, withhold_actions=withhold_actions)
    per_window = [] if args.per_window_out else None
    result = rollout_evaluate(model, loader, args, device, frame_scorer(args, dataset, device, "rollout"),
                              per_window, withhold_actions=withhold_actions)
    if per_window is not None:
        write_per_window(args.per_window_out, per_window, dataset, indices)
    return result


def run_per_window(args: argparse.Namespace) -> dict:
    device = start_process(args)
    return rollout_writing_windows(load_model(args, device), args, device)


def add_per_window_parser(subparsers) -> None:
    parser = _subparser(subparsers, "per_window", "evaluate.py's rollout protocol, also writing each window's own "
                                                  "scores to --per_window_out", PER_WINDOW_DOC)
    add_window_args(parser)
    add_prompt_arg(parser)
    add_per_window_arg(parser, "Required: ", required=True)
    parser.set_defaults(check=functools.partial(check_per_window, parser), run=run_per_window)


def check_per_window(parser, args: argparse.Namespace) -> None:
    check_window_args(parser, args)
    check_prompt_arg(parser, args)
    check_per_window_arg(parser, args)


# ------------------------------------------------------------------ breakdown
def run_breakdown(args: argparse.Namespace) -> dict:
    result = breakdown(args.per_window, args.val_data_dir, args.stream, args.column, args.bins,
                       args.num_prompt_frames, args.stride)
    for line in describe(result):
        print(line, file=sys.stderr)
    return result


def add_breakdown_parser(subparsers) -> None:
    parser = _subparser(subparsers, "breakdown", "a --per_window_out file's windows in groups by the walker's "
                                                 "motion in their futures: the PSNR gain over holding of each group",
                        BREAKDOWN_DOC)
    parser.add_argument("per_window", help="The JSON Lines file of per_window's (or copy_ceiling's, or "
                                           "withheld_actions') --per_window_out.")
    parser.add_argument("--val_data_dir", required=True,
                        help="Required: the token dataset that the run which wrote the file scored.")
    parser.add_argument("--stream", default="measured_motion",
                        help="Action stream that places each window (default: %(default)s).")
    parser.add_argument("--column", type=int, default=1,
                        help="Column of --stream (the sample world's measured_motion: 0 forward speed, 1 turn rate; "
                             "default: %(default)s).")
    parser.add_argument("--bins", type=int, default=3,
                        help="Groups of equal size to cut the windows into (default: %(default)s).")
    parser.add_argument("--num_prompt_frames", type=int, default=8,
                        help="The --num_prompt_frames of the run that wrote the file (default: %(default)s).")
    parser.add_argument("--stride", type=int, default=15,
                        help="The --stride of the run that wrote the file (default: %(default)s).")
    parser.set_defaults(check=functools.partial(check_breakdown, parser), run=run_breakdown)


def check_breakdown(parser, args: argparse.Namespace) -> None:
    for name in ("bins", "num_prompt_frames", "stride"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")


# ------------------------------------------------------------------ withheld_actions
def run_withheld_actions(args: argparse.Namespace) -> dict:
    device = start_process(args)
    model = load_model(args, device)
    if not model.config.uses_actions:
        raise DataMismatchError(f"withheld_actions: the checkpoint {args.checkpoint_dir} takes no actions to "
                                f"withhold (evaluate.py scores it as it is)")
    if args.protocol == "rollout":
        result = rollout_writing_windows(model, args, device, withhold_actions=True)
    else:
        dataset, _, loader = model_windows(model, args, withhold_actions=True)
        with torch.no_grad():
            result, _ = teacher_forced_run(model, loader, dataset, args, device, withhold_actions=True)
    return {**result, "actions_withheld": True}


def add_withheld_actions_parser(subparsers) -> None:
    parser = _subparser(subparsers, "withheld_actions", "evaluate.py's protocols on an action model given no "
                                                        "actions (every frame gets the learned 'no action' input)",
                        WITHHELD_ACTIONS_DOC)
    add_protocol_args(parser)
    add_window_args(parser)
    add_save_outputs_arg(parser)
    add_per_window_arg(parser, "Rollout protocol only: also ")
    parser.set_defaults(check=functools.partial(check_withheld_actions, parser), run=run_withheld_actions)


def check_withheld_actions(parser, args: argparse.Namespace) -> None:
    check_window_args(parser, args)
    check_protocol_args(parser, args)


# ------------------------------------------------------------------ control
def run_control(args: argparse.Namespace) -> dict:
    from evaluation.control_check import control_check
    from evaluation.protocols import example_indices
    from envs.pairing import real_world_for
    from envs.world_model import WorldModelEnv

    start_process(args)
    env = WorldModelEnv.from_checkpoint(args.checkpoint_dir, args.val_data_dir, args.tokenizer_ckpt,
                                        device="cpu", copy_bias=args.copy_bias, temperature=args.temperature,
                                        maskgit_steps=args.maskgit_steps)
    if not env.buttons:
        raise DataMismatchError(f"control: the checkpoint {args.checkpoint_dir} is not driven by the sample world's "
                                f"buttons (its action_names are {env.model.config.action_names})")
    real_env, raw_npz = (None, None) if args.no_real_world else real_world_for(env, args.val_data_dir)
    if real_env is None:
        logger.info("no real world to compare with: %s", raw_npz)
    starts = example_indices(len(env.starts), args.num_starts, spread=True)
    result = control_check(env, starts, args.steps, args.seed, real_env, raw_npz if real_env else None)
    for world in ("model", "real"):
        if result[world] is not None:
            r = result[world]
            logger.info("%s: mean shift per step %s px; opposite turns in %.0f %% of starts (left right, right "
                        "left in %.0f %%); forward less sideways than both turns in %.0f %%", world,
                        {a: round(v, 2) for a, v in r["mean_shift"].items()}, 100 * r["opposite_turns_share"],
                        100 * r["left_right_share"], 100 * r["forward_less_sideways_share"])
    return {"checkpoint_dir": str(args.checkpoint_dir), "val_data_dir": str(args.val_data_dir),
            "temperature": args.temperature, "seed": args.seed, **result}


CONTROL_DOC = """Does the model obey its controls? From --num_starts windows spread over --val_data_dir, the world model environment
holds TURN_LEFT, TURN_RIGHT and MOVE_FORWARD for --steps steps each, from the same start and sampler seed, and the
horizontal shift between consecutive frames is measured by phase correlation (pixels per step; positive: the image
moves right, as when the view turns left). The same starts and buttons are played in the real world beside when the
data is a sample world's split (evaluation/control_check.py). The JSON line has "model" and "real" summaries
(mean_shift per action, opposite_turns_share, left_right_share, forward_less_sideways_share,
forward_less_sideways_mean) and "per_start"."""


def add_control_parser(subparsers) -> None:
    parser = _subparser(subparsers, "control", "hold each button from the same starts: do the frames turn and walk "
                                               "as the button says?", CONTROL_DOC)
    parser.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt",
                        help="The model, driven by the sample world's buttons (default: %(default)s).")
    parser.add_argument("--val_data_dir", default="data/unseen/val",
                        help="Token dataset of the starts (default: %(default)s, maps never trained on).")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help="Tokenizer that decodes the frames (default: the one the data's metadata names).")
    parser.add_argument("--num_starts", type=int, default=24, help="Starts spread over the data (default: "
                                                                   "%(default)s).")
    parser.add_argument("--steps", type=int, default=8, help="Steps each button is held (default: %(default)s).")
    parser.add_argument("--temperature", type=float, default=1.0, help="Sampling temperature (default: %(default)s, "
                                                                       "play.py's).")
    parser.add_argument("--maskgit_steps", type=int, default=2, help="MaskGIT steps per frame (default: "
                                                                     "%(default)s).")
    parser.add_argument("--copy_bias", type=float, default=2.0, help="The copy head's bias (default: %(default)s).")
    parser.add_argument("--no_real_world", action="store_true", help="Do not play the real world as the reference.")
    parser.add_argument("--seed", type=int, default=0, help="Sampler seed of the first start (default: %(default)s).")
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--num_threads", type=int, default=0, help="CPU threads (0: torch's default).")
    parser.set_defaults(check=functools.partial(check_control, parser), run=run_control)


def check_control(parser, args: argparse.Namespace) -> None:
    for name in ("num_starts", "steps", "maskgit_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.temperature < 0:
        parser.error(f"--temperature must be >= 0, got {args.temperature}")


# ------------------------------------------------------------------ command line
def _subparser(subparsers, name: str, summary: str, description: str) -> argparse.ArgumentParser:
    return subparsers.add_parser(name, help=summary, description=description,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND",
                                       help="the diagnostic to run (`%(prog)s SUBCOMMAND --help` lists its flags)")
    add_copy_ceiling_parser(subparsers)
    add_per_window_parser(subparsers)
    add_breakdown_parser(subparsers)
    add_withheld_actions_parser(subparsers)
    add_control_parser(subparsers)
    return parser


def parse_args(argv=None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.check(args)
    return args


def main(argv=None) -> int:
    setup_logging()
    args = parse_args(argv)
    print(json.dumps(args.run(args)))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("evaluation.diagnostics", main))
