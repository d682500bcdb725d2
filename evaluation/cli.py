"""The flags of the commands that evaluate a model (evaluate.py, diagnose.py) and of every command that samples one
(generate.py, play.py): defined once here, checked here, and turned into the evaluation's dataclasses
(`eval_config`, `decoding_overrides`). Entry points only: the evaluation package itself never reads flags.

The decoding flags default to nothing: a model decodes as its checkpoint's decoding.json says (genie/decoding.py),
and a flag given overrides that one value.
"""
import argparse
import dataclasses
from pathlib import Path
from typing import Optional, Tuple

from common.cli import add_device_arg, add_num_threads_arg, finite_float
from genie.decoding import GREEDY_TOKEN_CHOICES, UNMASK_MODES, DecodingConfig
from evaluation.protocols import (DEFAULT_CHECKPOINT, DEFAULT_ROLLOUT_PROMPT_FRAMES, DEFAULT_TOKENIZER, DEFAULT_VAL_DIR,
                                  PROTOCOLS, SAMPLE_VAL_DIR, EvalConfig, default_val_data_dir)
from evaluation.policy_ranking import DEFAULT_MAPS, PolicyRankingConfig
from sample_world.render import map_name

DECODING_FIELDS = tuple(f.name for f in dataclasses.fields(DecodingConfig))


# ------------------------------------------------------------------ decoding
def add_decoding_args(parser) -> None:
    """--maskgit_steps, --temperature, --unmask_mode, --copy_bias, --greedy_tokens and --stall_ratio, in a group of
    their own in --help, each unset by default (the checkpoint's decoding). `decoding_overrides` collects them."""
    group = parser.add_argument_group(
        "decoding", "How frames are sampled from the model. Each flag overrides one value of the checkpoint's "
                    "decoding.json (what the model was meant to be sampled with; a checkpoint without one, such as "
                    "the published GENIE_35M, decodes as the published code: 2 MaskGIT steps, greedy, no copy bias). "
                    "The teacher-forced protocol scores the checkpoint's MaskGIT steps greedily, without copy bias, "
                    "unless these flags say otherwise.")
    defaults = DecodingConfig()
    group.add_argument("--maskgit_steps", type=int, default=None,
                       help=f"MaskGIT sampling steps per frame, >= 1 (published: {defaults.maskgit_steps}).")
    group.add_argument("--temperature", type=finite_float, default=None,
                       help="Sampling temperature (divides the logits), >= 0; 0 samples greedily (argmax). A model "
                            "with a copy head draws whole tokens from its copy-or-new mixture.")
    group.add_argument("--unmask_mode", choices=UNMASK_MODES, default=None,
                       help="Which tokens each MaskGIT step reveals: random (the published default) or the most "
                            "confident (greedy).")
    group.add_argument("--copy_bias", type=finite_float, default=None,
                       help="Models with a copy head (copy_radius) only: added to every previous-frame neighbour's "
                            "score when sampling (e^bias times the copy weight). > 0 gives sharper futures closer to "
                            "the previous frame (better LPIPS, lower PSNR); 0 is the model as trained.")
    described = "; ".join(f"{name}: {what}" for name, what in GREEDY_TOKEN_CHOICES.items())
    group.add_argument("--greedy_tokens", choices=tuple(GREEDY_TOKEN_CHOICES), default=None,
                       help=f"How greedy decoding (--temperature 0) picks each token of a model with a copy head "
                            f"(copy_radius): {described}. Models without a copy head decode the same either way.")
    group.add_argument("--stall_ratio", type=_share, default=None,
                       help="Decoding rule for free-running futures, off unless the checkpoint sets it: once a "
                            "generated frame changes at most this fraction of what the prompt's frames change per "
                            "step (the share of tokens that differ from the frame before; a number in (0, 1], e.g. "
                            "0.66), the window's future is taken to have stopped moving and every later frame "
                            "repeats that one. Needs at least 2 prompt frames. Teacher-forced predictions are "
                            "unaffected.")


def _share(text: str) -> float:
    """argparse type of a share in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}") from None
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text}")
    return value


def check_decoding_args(parser, args: argparse.Namespace, num_prompt_frames: Optional[int] = None) -> None:
    """Usage errors for decoding flags out of range; with `num_prompt_frames` (the prompt of free-running futures),
    also for a --stall_ratio that the prompt cannot measure."""
    if args.maskgit_steps is not None and args.maskgit_steps < 1:
        parser.error(f"--maskgit_steps must be >= 1, got {args.maskgit_steps}")
    if args.temperature is not None and args.temperature < 0:
        parser.error(f"--temperature must be >= 0, got {args.temperature}")
    if num_prompt_frames is not None and args.stall_ratio is not None and num_prompt_frames < 2:
        parser.error(f"--stall_ratio compares generated frames with the prompt's motion: it needs --num_prompt_frames "
                     f">= 2, got {num_prompt_frames}")


def decoding_overrides(args: argparse.Namespace) -> dict:
    """The decoding flags that were given: {field: value} (genie.decoding.DecodingConfig.override)."""
    return {name: getattr(args, name) for name in DECODING_FIELDS if getattr(args, name, None) is not None}


def eval_config(args: argparse.Namespace) -> EvalConfig:
    """The EvalConfig of a parsed command line (its flags of the same names; the decoding flags as overrides)."""
    names = {f.name for f in dataclasses.fields(EvalConfig)} - {"decoding"}
    values = {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
    return EvalConfig(**values, decoding=decoding_overrides(args))


# ------------------------------------------------------------------ windows and protocols
def add_window_args(parser, checkpoint: bool = True) -> None:
    """The flags of every evaluation: the validation windows, frame decoding and scoring, the device; and unless
    `checkpoint` is False (a diagnostic without a model), the checkpoint, the sampler's seed and the decoding flags
    (genie/decoding.py). Check them with `check_window_args`."""
    parser.add_argument("--val_data_dir", default=None,
                        help=f"Token dataset to evaluate on (default: {DEFAULT_VAL_DIR}, or {SAMPLE_VAL_DIR} when "
                             f"only that exists).")
    if checkpoint:
        parser.add_argument("--checkpoint_dir", default=DEFAULT_CHECKPOINT,
                            help="GENIE checkpoint directory (config.json + model.safetensors) or a Hugging Face hub "
                                 "id such as 1x-technologies/GENIE_35M (default: %(default)s).")
    parser.add_argument("--window_size", type=int, default=16,
                        help="Frames per validation window, >= 2 (default: %(default)s; at most the checkpoint's T).")
    parser.add_argument("--stride", type=int, default=15,
                        help="Frames of the dataset between a window's frames (default: %(default)s: 30 Hz / 15 = "
                             "2 Hz). Windows do not overlap.")
    parser.add_argument("--max_examples", type=int, default=None,
                        help="Evaluate only N validation windows (keeps CPU runs short): the first N, or N evenly "
                             "spaced over the dataset with --spread_examples (default: all).")
    parser.add_argument("--spread_examples", action="store_true",
                        help="With --max_examples: take the N windows evenly spaced over the whole dataset (every "
                             "episode and map represented) instead of the first N (the start of the first episodes).")
    parser.add_argument("--batch_size", type=int, default=16, help="Windows per forward pass (default: %(default)s).")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help="MAGVIT2 tokenizer that decodes token frames to pixels for LPIPS, PSNR and SSIM "
                             f"(default: the dataset metadata's tokenizer_ckpt, else {DEFAULT_TOKENIZER}).")
    parser.add_argument("--skip_lpips", action="store_true",
                        help="Skip LPIPS (no LPIPS weights needed): the LPIPS keys are null. Teacher-forced: nothing "
                             "is decoded either (no tokenizer needed; dec_time null). Rollout (and the "
                             "diagnostics that score futures): frames are still decoded for PSNR / SSIM.")
    add_device_arg(parser)
    add_num_threads_arg(parser)
    if checkpoint:
        parser.add_argument("--seed", type=int, default=0,
                            help="Seed of the sampler's random numbers (default: %(default)s).")
        add_decoding_args(parser)
    else:  # nothing random to seed
        parser.set_defaults(seed=0)


def add_protocol_args(parser, more: Tuple[str, ...] = (), more_help: str = "") -> None:
    """--protocol (teacher_forced or rollout, and the protocols `more` that `more_help` describes) and
    --num_prompt_frames (rollout only); check with `check_protocol_args`."""
    parser.add_argument("--protocol", choices=PROTOCOLS + tuple(more), default=PROTOCOLS[0],
                        help="teacher_forced (default): each frame predicted from the ground-truth frames before it, "
                             "scored by CE, token accuracy, LPIPS and s/frame; rollout: prompt with the first "
                             "--num_prompt_frames frames of each window, generate the rest free-running, score PSNR "
                             "/ SSIM / LPIPS per horizon against holding the last prompt frame" + more_help + ".")
    add_prompt_arg(parser, "Rollout protocol only: ")


def add_prompt_arg(parser, applies: str = "") -> None:
    """--num_prompt_frames of the free-running futures (default None: `check_prompt_arg` sets it)."""
    parser.add_argument("--num_prompt_frames", type=int, default=None,
                        help=f"{applies}ground-truth prompt frames P per window, 1 <= P < --window_size (default "
                             f"{DEFAULT_ROLLOUT_PROMPT_FRAMES}); the other window_size - P frames are generated.")


def add_save_outputs_arg(parser) -> None:
    parser.add_argument("--save_outputs_dir", default=None,
                        help="Teacher-forced protocol only: write the predictions as a token dataset in the generated "
                             "layout (per window: frame 0 | predicted frames 1..T-1 | ground truth frames 1..T-1).")


def add_per_window_arg(parser, applies: str = "", required: bool = False) -> None:
    parser.add_argument("--per_window_out", default=None, required=required,
                        help=f"{applies}write the scores of each window alone to this JSON Lines file (one line per "
                             f"window, written when the run ends): window (its index among the dataset's windows), "
                             f"first_frame (its first frame in video.bin), segment_id (when the dataset has "
                             f"segment_ids.bin), and every per-horizon list of the summary (rollout_psnr, hold_psnr, "
                             f"..., true_repeated) for that window; the summary's lists are their means. "
                             f"`python -m evaluation.diagnostics breakdown` groups them by the walker's motion.")


def check_window_args(parser, args: argparse.Namespace) -> None:
    """Usage errors of `add_window_args`' flags; fills in --val_data_dir's default."""
    if args.batch_size < 1:
        parser.error(f"--batch_size must be >= 1, got {args.batch_size}")
    if args.max_examples is not None and args.max_examples < 1:
        parser.error(f"--max_examples must be >= 1, got {args.max_examples}")
    if args.window_size < 2:
        parser.error("--window_size must be >= 2 (frame 0 is the first prompt, frames 1.. are predicted)")
    if args.stride < 1:
        parser.error(f"--stride must be >= 1, got {args.stride}")
    if hasattr(args, "maskgit_steps"):
        check_decoding_args(parser, args)
    if args.val_data_dir is None:
        args.val_data_dir = default_val_data_dir()


def check_prompt_arg(parser, args: argparse.Namespace) -> None:
    """--num_prompt_frames of free-running futures: its default, its range, and --stall_ratio's need of 2."""
    if args.num_prompt_frames is None:
        args.num_prompt_frames = DEFAULT_ROLLOUT_PROMPT_FRAMES
    if not 1 <= args.num_prompt_frames < args.window_size:
        parser.error(f"--num_prompt_frames must be in 1..{args.window_size - 1} (at least one prompt frame and one "
                     f"frame to generate in windows of --window_size {args.window_size}), got "
                     f"{args.num_prompt_frames}")
    if hasattr(args, "stall_ratio"):
        check_decoding_args(parser, args, args.num_prompt_frames)


def check_per_window_arg(parser, args: argparse.Namespace) -> None:
    if args.per_window_out is not None and Path(args.per_window_out).is_dir():
        parser.error(f"--per_window_out is a file to write; {args.per_window_out} is a directory")


def check_protocol_args(parser, args: argparse.Namespace) -> None:
    """Usage errors of flags that one protocol only takes (`add_protocol_args`, `add_save_outputs_arg`,
    `add_per_window_arg` where the parser has them)."""
    per_window = getattr(args, "per_window_out", None)
    if args.protocol == "play":
        if args.save_outputs_dir is not None:
            parser.error("--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol play")
        if args.play_steps < 1 or args.starts_per_episode < 1:
            parser.error(f"--play_steps and --starts_per_episode must be >= 1, got {args.play_steps} and "
                         f"{args.starts_per_episode}")
        return
    if getattr(args, "figures_dir", None) is not None:
        parser.error("--figures_dir applies to --protocol play only")
    if args.protocol == "policies":
        if args.save_outputs_dir is not None:
            parser.error("--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol "
                         "policies")
        return
    if args.protocol == "rollout":
        check_prompt_arg(parser, args)
        if args.save_outputs_dir is not None:
            parser.error("--save_outputs_dir writes teacher-forced predictions; it does not apply to --protocol "
                         "rollout")
        if per_window is not None:
            check_per_window_arg(parser, args)
    else:
        if args.num_prompt_frames is not None:
            parser.error("--num_prompt_frames applies to --protocol rollout only")
        if per_window is not None:
            parser.error("--per_window_out applies to --protocol rollout only (the teacher-forced protocol's "
                         "predictions: --save_outputs_dir)")


# ------------------------------------------------------------------ the play protocol
PLAY_HELP = ("; play: from real starts of a sample world split, replay each recorded walk's buttons for --play_steps "
             "steps and score every step against the real frames (PSNR, LPIPS, sharpness, KID per horizon bin) beside "
             "the tokenizer's reconstruction and holding the last real frame (evaluation/play_protocol.py)")


def add_play_args(parser) -> None:
    group = parser.add_argument_group("play protocol", "What a player sees, against the real pixels (--protocol "
                                                       "play; --num_prompt_frames: real frames given, default the "
                                                       "model's; the decoding flags override the model's sampler).")
    group.add_argument("--play_steps", type=int, default=64,
                       help="Steps of play from each start, 15 tics each (default: %(default)s, 27 s).")
    group.add_argument("--starts_per_episode", type=int, default=2,
                       help="Starts spread over each recorded walk (default: %(default)s).")
    group.add_argument("--figures_dir", default=None,
                       help="Write play_curves.png (the scores per step and KID per bin) and play_drive.gif (the "
                            "first start's drive: model | tokenizer | real) here (default: none).")


def play_config(args: argparse.Namespace):
    """The PlayConfig of evaluate.py's parsed command line."""
    from evaluation.play_protocol import PlayConfig

    return PlayConfig(data_dir=args.val_data_dir, checkpoint_dir=args.checkpoint_dir, steps=args.play_steps,
                      starts_per_episode=args.starts_per_episode, prompt_frames=args.num_prompt_frames,
                      tokenizer_ckpt=args.tokenizer_ckpt, decoding=decoding_overrides(args), seed=args.seed,
                      figures_dir=args.figures_dir, device=args.device, num_threads=args.num_threads)


# ------------------------------------------------------------------ the policies protocol
POLICIES_HELP = ("; policies: rank --policies by how far each gets from its start in --steps steps, inside the world "
                 "model and in the real sample world, from the same starts (evaluation/policy_ranking.py)")


def add_policy_args(parser) -> None:
    from sample_world.policies import BUILTIN_POLICIES

    group = parser.add_argument_group("policies protocol", "Ranking policies inside the world model (--protocol "
                                                           "policies; the decoding flags override the model's "
                                                           "sampler).")
    group.add_argument("--policies", nargs="+", default=list(BUILTIN_POLICIES),
                       help="Built-in policy names or path/to/file.py:ClassName (default: the built-in suite, "
                            "%(default)s).")
    group.add_argument("--maps", nargs="+", type=map_name, default=list(DEFAULT_MAPS),
                       help="Maps of the starts (default: %(default)s, never trained on).")
    group.add_argument("--starts", type=int, default=4, help="Starts per map (default: %(default)s).")
    group.add_argument("--steps", type=int, default=16,
                       help="Window steps each policy drives, 15 tics each (default: %(default)s, 6.9 s).")
    group.add_argument("--policy_dir", default="data/policies",
                       help="Where the cloned policies and the motion estimator are kept; trained there on first use "
                            "from --policy_train_data (default: %(default)s).")
    group.add_argument("--policy_train_data", default="data/sample/raw/train.npz",
                       help="Recorded walks (frames, buttons, measured motion) that the cloned policies and the "
                            "motion estimator learn from (default: %(default)s).")


def check_policy_args(parser, args) -> None:
    for name in ("starts", "steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")




def policy_config(args: argparse.Namespace) -> PolicyRankingConfig:
    """The PolicyRankingConfig of evaluate.py's parsed command line."""
    return PolicyRankingConfig(
        checkpoint_dir=args.checkpoint_dir, policies=list(args.policies), maps=list(args.maps), starts=args.starts,
        steps=args.steps, seed=args.seed, num_prompt_frames=args.num_prompt_frames,
        tokenizer_ckpt=args.tokenizer_ckpt, decoding=decoding_overrides(args), policy_dir=args.policy_dir,
        policy_train_data=args.policy_train_data, device=args.device, num_threads=args.num_threads)
