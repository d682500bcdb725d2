#!/usr/bin/env python
"""Diagnostics of a dynamics model's futures and of the data, scored like evaluate.py's protocols: one subcommand
each (`python diagnose.py SUBCOMMAND --help` explains it and its flags), one JSON line on stdout (the last line;
progress goes to stderr).

    python diagnose.py copy_ceiling --ceiling_block 8 --max_examples 48 --spread_examples
    python diagnose.py per_window --per_window_out windows.jsonl --max_examples 48 --spread_examples
    python diagnose.py breakdown windows.jsonl --val_data_dir data/sample/val --column 1
    python diagnose.py withheld_actions --protocol rollout --max_examples 48
    python diagnose.py control --val_data_dir data/unseen/val --num_starts 24
    python diagnose.py baselines --train_data_dir data/sample/train --val_data_dir data/sample/val
"""
import argparse
import functools
import json
import sys

from common.cli import add_num_threads_arg, run_main, setup_logging
from common.shutdown import exit_on_sigterm
from evaluation.baselines import baselines
from evaluation.cli import (add_decoding_args, add_per_window_arg, add_prompt_arg, add_protocol_args,
                            add_save_outputs_arg, add_window_args, check_decoding_args, check_per_window_arg,
                            check_prompt_arg, check_protocol_args, check_window_args, decoding_overrides, eval_config)
from evaluation.diagnostics import (ControlConfig, run_control, run_copy_ceiling, run_per_window,
                                    run_withheld_actions)
from evaluation.rollout_breakdown import breakdown, describe

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
measured_motion column 1 is the turn rate, column 0 the forward speed, as measured). Each group's futures are
compared with holding the last prompt frame per horizon (evaluation/rollout_breakdown.py): a mean over all windows
can hide a group of windows where the futures lose to holding; this shows which motion it is. One readable line per
group goes to stderr; the JSON line is {"stream", "column", "groups": [{"low", "high", "num_windows", "psnr_gain"
(dB per horizon), "psnr_gain_mean", "lpips_rollout", "lpips_hold" (null when the file has no LPIPS)}, ...]}."""

WITHHELD_ACTIONS_DOC = """\
evaluate.py's protocols (the same flags) on a model with action inputs that is given none: every frame gets the
learned "no action" input that training's action dropout teaches, to measure what the model predicts from the
frames alone; the dataset needs no action streams. The JSON line is the protocol's, without the latent-action
metrics (delta_psnr, the probe), plus "actions_withheld": true."""

CONTROL_DOC = """\
Does the model obey its controls? From --num_starts windows spread over --val_data_dir, the world model environment
holds each button alone (TURN_LEFT, TURN_RIGHT, MOVE_FORWARD, MOVE_BACKWARD, USE) and NONE (no button) for --steps
steps, from the same start and sampler seed. Each pair of consecutive frames gives the horizontal shift by phase
correlation (pixels per step; positive: the image moves right, as when the view turns left) and the forward motion:
the motion estimator's (--motion_estimator, map units; the policies protocol trains it) when that file exists, else
the zoom of the image about its centre (percent; positive: growing, as when walking forward). The checks: the turns
shift the image opposite ways, forward shifts it less sideways than the turns, forward moves forward and backward
back, NONE and USE alone keep it still (under a quarter of forward's motion and of the turns' shift). The same
starts and controls are played in the real world beside when the data is a sample world's split
(evaluation/control_check.py). The model decodes as its checkpoint says unless the decoding flags override it. The
JSON line has "model" and "real" summaries (mean_shift and mean_forward per control, "checks" and "passed", the
shares of starts where each control shows: opposite_turns_share, left_right_share, forward_less_sideways_share,
forward_share, backward_share, forward_backward_share, none_still_share, use_still_share), "forward_measure",
"per_start" and the "decoding" used."""

BASELINES_DOC = """\
The baselines of a validation split, the same for every model (evaluation/baselines.py): copying the last frame's
tokens (and its expected accuracy from the factor match rate p of the training split), and lookup tables from the
training split's transitions. The JSON line: copy_acc and its expectation, lookup_acc, factored_lookup_acc,
num_examples."""


# ------------------------------------------------------------------ copy_ceiling
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
    parser.set_defaults(check=functools.partial(check_copy_ceiling, parser),
                        run=lambda args: run_copy_ceiling(eval_config(args), args.ceiling_radius,
                                                          args.ceiling_block, args.per_window_out))


def check_copy_ceiling(parser, args: argparse.Namespace) -> None:
    check_window_args(parser, args)
    if args.ceiling_radius < 0 or args.ceiling_block < 1:
        parser.error(f"--ceiling_radius must be >= 0 and --ceiling_block >= 1, got {args.ceiling_radius} and "
                     f"{args.ceiling_block}")
    check_prompt_arg(parser, args)
    check_per_window_arg(parser, args)


# ------------------------------------------------------------------ per_window
def add_per_window_parser(subparsers) -> None:
    parser = _subparser(subparsers, "per_window", "evaluate.py's rollout protocol, also writing each window's own "
                                                  "scores to --per_window_out", PER_WINDOW_DOC)
    add_window_args(parser)
    add_prompt_arg(parser)
    add_per_window_arg(parser, "Required: ", required=True)
    parser.set_defaults(check=functools.partial(check_per_window, parser),
                        run=lambda args: run_per_window(eval_config(args), args.per_window_out))


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
    parser.set_defaults(check=functools.partial(check_minimums, parser, ("bins", "num_prompt_frames", "stride")),
                        run=run_breakdown)


def check_minimums(parser, names, args: argparse.Namespace, minimum: int = 1) -> None:
    """Usage errors for the integer flags `names` below `minimum` (None: unset, allowed)."""
    for name in names:
        value = getattr(args, name)
        if value is not None and value < minimum:
            parser.error(f"--{name} must be >= {minimum}, got {value}")


# ------------------------------------------------------------------ withheld_actions
def add_withheld_actions_parser(subparsers) -> None:
    parser = _subparser(subparsers, "withheld_actions", "evaluate.py's protocols on an action model given no "
                                                        "actions (every frame gets the learned 'no action' input)",
                        WITHHELD_ACTIONS_DOC)
    add_protocol_args(parser)
    add_window_args(parser)
    add_save_outputs_arg(parser)
    add_per_window_arg(parser, "Rollout protocol only: also ")
    parser.set_defaults(check=functools.partial(check_withheld_actions, parser),
                        run=lambda args: run_withheld_actions(eval_config(args), args.protocol, args.per_window_out))


def check_withheld_actions(parser, args: argparse.Namespace) -> None:
    check_window_args(parser, args)
    check_protocol_args(parser, args)


# ------------------------------------------------------------------ control
def add_control_parser(subparsers) -> None:
    parser = _subparser(subparsers, "control", "hold each button from the same starts: do the frames turn and walk "
                                               "as the button says?", CONTROL_DOC)
    defaults = ControlConfig()
    parser.add_argument("--checkpoint_dir", default=defaults.checkpoint_dir,
                        help="The model, driven by the sample world's buttons (default: %(default)s).")
    parser.add_argument("--val_data_dir", default=defaults.val_data_dir,
                        help="Token dataset of the starts (default: %(default)s, maps never trained on).")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help="Tokenizer that decodes the frames (default: the one the data's metadata names).")
    parser.add_argument("--num_starts", type=int, default=defaults.num_starts,
                        help="Starts spread over the data (default: %(default)s).")
    parser.add_argument("--steps", type=int, default=defaults.steps,
                        help="Steps each button is held (default: %(default)s).")
    parser.add_argument("--no_real_world", action="store_true", help="Do not play the real world as the reference.")
    parser.add_argument("--motion_estimator", default=defaults.motion_estimator,
                        help="Motion estimator weights that measure forward motion (default: %(default)s); when the "
                             "file is missing, the zoom between frames does.")
    parser.add_argument("--seed", type=int, default=defaults.seed,
                        help="Sampler seed of the first start (default: %(default)s).")
    add_num_threads_arg(parser)
    add_decoding_args(parser)
    parser.set_defaults(check=functools.partial(check_control, parser), run=run_control_args)


def check_control(parser, args: argparse.Namespace) -> None:
    check_minimums(parser, ("num_starts", "steps"), args)
    check_decoding_args(parser, args)


def run_control_args(args: argparse.Namespace) -> dict:
    return run_control(ControlConfig(
        checkpoint_dir=args.checkpoint_dir, val_data_dir=args.val_data_dir, tokenizer_ckpt=args.tokenizer_ckpt,
        num_starts=args.num_starts, steps=args.steps, seed=args.seed, decoding=decoding_overrides(args),
        real_world=not args.no_real_world, num_threads=args.num_threads, motion_estimator=args.motion_estimator))


# ------------------------------------------------------------------ baselines
def add_baselines_parser(subparsers) -> None:
    parser = _subparser(subparsers, "baselines", "the data's baselines: copying the last frame, lookup tables",
                        BASELINES_DOC)
    parser.add_argument("--train_data_dir", default="data/sample/train",
                        help="Split used to fit p and the lookup tables (default: %(default)s).")
    parser.add_argument("--val_data_dir", default="data/sample/val",
                        help="Split the baselines are measured on (default: %(default)s).")
    parser.add_argument("--window_size", type=int, default=16, help="Frames per window (default: %(default)s).")
    parser.add_argument("--stride", type=int, default=15,
                        help="Frames between consecutive window frames (default: %(default)s).")
    parser.add_argument("--num_factored_vocabs", type=int, default=2,
                        help="Factors per token id (default: %(default)s).")
    parser.add_argument("--max_train_windows", type=int, default=2000,
                        help="Training windows (non-overlapping) used to fit p and the lookup tables (default: "
                             "%(default)s).")
    parser.add_argument("--max_examples", type=int, default=None,
                        help="Validation windows to use (default: all).")
    parser.set_defaults(check=functools.partial(check_baselines, parser), run=run_baselines)


def check_baselines(parser, args: argparse.Namespace) -> None:
    check_minimums(parser, ("window_size",), args, minimum=2)
    check_minimums(parser, ("stride", "num_factored_vocabs", "max_train_windows", "max_examples"), args)


def run_baselines(args: argparse.Namespace) -> dict:
    return baselines(args.train_data_dir, args.val_data_dir, args.window_size, args.stride, args.num_factored_vocabs,
                     args.max_train_windows, args.max_examples)


# ------------------------------------------------------------------ command line
def _subparser(subparsers, name: str, summary: str, description: str) -> argparse.ArgumentParser:
    return subparsers.add_parser(name, help=summary, description=description,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diagnose.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND",
                                       help="the diagnostic to run (`%(prog)s SUBCOMMAND --help` lists its flags)")
    add_copy_ceiling_parser(subparsers)
    add_per_window_parser(subparsers)
    add_breakdown_parser(subparsers)
    add_withheld_actions_parser(subparsers)
    add_control_parser(subparsers)
    add_baselines_parser(subparsers)
    return parser


def parse_args(argv=None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.check(args)
    return args


def main(argv=None) -> int:
    setup_logging()
    exit_on_sigterm()  # the control check starts ViZDoom engines: SIGTERM closes them, as Ctrl-C does
    args = parse_args(argv)
    print(json.dumps(args.run(args)))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("diagnose.py", main))
