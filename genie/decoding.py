"""The decoding flags of every command that samples frames from a dynamics model (evaluate.py, genie/generate.py,
python -m genie.diagnostics), defined once here, and the functions that check them and apply them to a model.

    --maskgit_steps, --temperature, --unmask_mode: the MaskGIT sampler (genie.sampling);
    --copy_bias, --greedy_tokens: how a model with a copy head (copy_radius) turns its copy-or-new mixture into
        tokens (STMaskGIT.set_copy_bias, STMaskGIT.set_greedy_tokens); sampling at a temperature always draws whole
        tokens from that mixture;
    --stall_ratio: the stall rule of free-running futures (genie.inference.generate).
"""
import argparse
from typing import Optional

from common.cli import finite_float
from common.errors import DataMismatchError
from genie.sampling import UNMASK_MODES

# how greedy decoding (--temperature 0) picks each token of a model with a copy head: choice -> what it does (the
# first is the default)
GREEDY_TOKEN_CHOICES = {
    "joint": "the most probable whole token of the mixture",
    "best_neighbour": "as joint, but a copy takes the single most weighted neighbour's token, not the token with the "
                      "most weight summed over the neighbours holding it (which grows flat patches in rollouts)",
}
DEFAULT_MASKGIT_STEPS = 2


def add_decoding_args(parser) -> None:
    """--maskgit_steps, --temperature, --unmask_mode, --copy_bias, --greedy_tokens and --stall_ratio, in a group of
    their own in --help. Check them with `check_decoding_args`, apply them with `apply_decoding`."""
    group = parser.add_argument_group("decoding", "How frames are sampled from the model (the same flags in "
                                                  "evaluate.py, genie/generate.py and genie.diagnostics).")
    group.add_argument("--maskgit_steps", type=int, default=DEFAULT_MASKGIT_STEPS,
                       help="MaskGIT sampling steps per frame, >= 1 (default: %(default)s).")
    group.add_argument("--temperature", type=finite_float, default=0.0,
                       help="Sampling temperature (divides the logits), >= 0; 0 samples greedily (argmax) "
                            "(default: %(default)s). A model with a copy head draws whole tokens from its "
                            "copy-or-new mixture.")
    group.add_argument("--unmask_mode", choices=UNMASK_MODES, default=UNMASK_MODES[0],
                       help="Which tokens each MaskGIT step reveals: random (the published default) or the most "
                            "confident (greedy) (default: %(default)s).")
    group.add_argument("--copy_bias", type=finite_float, default=0.0,
                       help="Models with a copy head (copy_radius) only: added to every previous-frame neighbour's "
                            "score when sampling (e^bias times the copy weight). > 0 gives sharper futures closer to "
                            "the previous frame (better LPIPS, lower PSNR); 0 is the model as trained (default: "
                            "%(default)s).")
    add_token_choice_args(group)
    add_stall_ratio_arg(group)


def add_token_choice_args(parser) -> None:
    """--greedy_tokens (STMaskGIT.set_greedy_tokens)."""
    described = "; ".join(f"{name}: {what}" for name, what in GREEDY_TOKEN_CHOICES.items())
    parser.add_argument("--greedy_tokens", choices=tuple(GREEDY_TOKEN_CHOICES),
                        default=next(iter(GREEDY_TOKEN_CHOICES)),
                        help=f"How greedy decoding (--temperature 0) picks each token of a model with a copy head "
                             f"(copy_radius): {described} (default: %(default)s). Models without a copy head decode "
                             f"the same either way.")


def _share(text: str) -> float:
    """argparse type of a share in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}") from None
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text}")
    return value


def add_stall_ratio_arg(parser) -> None:
    """--stall_ratio (genie.inference.generate's stall rule)."""
    parser.add_argument("--stall_ratio", type=_share, default=None,
                        help="Decoding rule for free-running futures, off by default: once a generated frame changes "
                             "at most this fraction of what the prompt's frames change per step (the share of "
                             "tokens that differ from the frame before; a number in (0, 1], e.g. 0.66), the "
                             "window's future is taken to have stopped moving and every later frame repeats that "
                             "one. A small model's greedy futures slow down and then decay in place; this holds "
                             "them where they stopped. Needs at least 2 prompt frames. Teacher-forced predictions "
                             "are unaffected.")


def check_stall_ratio(parser, stall_ratio: Optional[float], num_prompt_frames: int) -> None:
    """Usage error when --stall_ratio is set but the prompt has fewer than the 2 frames its motion is measured on."""
    if stall_ratio is not None and num_prompt_frames < 2:
        parser.error(f"--stall_ratio compares generated frames with the prompt's motion: it needs --num_prompt_frames "
                     f">= 2, got {num_prompt_frames}")


def check_decoding_args(parser, args: argparse.Namespace, num_prompt_frames: Optional[int] = None) -> None:
    """Usage errors for decoding flags out of range; with `num_prompt_frames` (the prompt of free-running futures),
    also for a --stall_ratio that the prompt cannot measure."""
    if args.maskgit_steps < 1:
        parser.error(f"--maskgit_steps must be >= 1, got {args.maskgit_steps}")
    if args.temperature < 0:
        parser.error(f"--temperature must be >= 0, got {args.temperature}")
    if num_prompt_frames is not None:
        check_stall_ratio(parser, args.stall_ratio, num_prompt_frames)


def apply_decoding(model, args: argparse.Namespace, checkpoint) -> None:
    """Set --copy_bias and --greedy_tokens on `model` (an STMaskGIT read from `checkpoint`, named in the error);
    DataMismatchError when --copy_bias is set for a model without a copy head."""
    if args.copy_bias and model.copy_head is None:
        raise DataMismatchError(f"--copy_bias: the checkpoint {checkpoint} has no copy head (copy_radius)")
    model.set_copy_bias(args.copy_bias)
    model.set_greedy_tokens(args.greedy_tokens)


def sampler_kwargs(args: argparse.Namespace) -> dict:
    """The keyword arguments of genie.inference.generate / teacher_forced that the flags set (not the stall rule,
    which only free-running generation takes)."""
    return dict(maskgit_steps=args.maskgit_steps, temperature=args.temperature, unmask_mode=args.unmask_mode)


def decoding_settings(args: argparse.Namespace) -> dict:
    """The sampler as results record it: maskgit_steps, temperature, copy_bias, greedy_tokens, stall_ratio."""
    return {"maskgit_steps": args.maskgit_steps, "temperature": args.temperature, "copy_bias": args.copy_bias,
            "greedy_tokens": args.greedy_tokens, "stall_ratio": args.stall_ratio}
