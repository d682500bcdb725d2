"""Command-line helpers shared by every script: the --device and --num_threads flags, and one logging set-up."""
import argparse
import logging
import math
from pathlib import Path

import torch

from common.allocator import retain_freed_memory

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%H:%M:%S"


def setup_logging(level: int = logging.INFO) -> None:
    """The one log format of all scripts (stderr, so that stdout stays free for results such as JSON lines)."""
    logging.basicConfig(format=LOG_FORMAT, datefmt=LOG_DATE_FORMAT, level=level)


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; any other torch device name must exist on this machine."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}: use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r}: CUDA is not available on this machine (use --device cpu or auto)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {name!r}: MPS is not available on this machine (use --device cpu or auto)")
    return device


# /proc/cpuinfo flag names of native bf16 arithmetic: x86 (AVX512-BF16, AMX) and Arm (FEAT_BF16)
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
NO_NATIVE_BF16 = f"none of {', '.join(NATIVE_BF16_FLAGS)} among the CPU's /proc/cpuinfo flags"


def cpu_has_native_bf16(cpuinfo: str = "/proc/cpuinfo") -> bool | None:
    """Whether this CPU computes bf16 natively, read from its feature flags; None where they cannot be read.

    torch's own check (mkldnn) accepts any AVX-512 CPU, where bf16 is emulated and slower than fp32.
    """
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return None
    flags = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            flags.update(value.split())
    if not flags:
        return None
    return not flags.isdisjoint(NATIVE_BF16_FLAGS)


def _device_name(name: str) -> str:
    """argparse type of --device: checked at parse time (a clear usage error), kept as the name the user gave."""
    try:
        resolve_device(name)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return name


def add_device_arg(parser, help: str = "torch device: auto (cuda when available, else cpu), cpu, cuda or cuda:N",
                   **kwargs) -> None:
    """--device, default 'auto'; scripts turn it into a torch.device with resolve_device(args.device)."""
    parser.add_argument("--device", type=_device_name, default="auto", help=help, **kwargs)


# how a model with a copy head (copy_radius) turns its copy-or-new mixture into tokens, per decoding mode:
# (flag, when it applies, its choices, what each does; the first is the default)
TOKEN_CHOICES = (
    ("--greedy_tokens", "greedy decoding (--temperature 0) picks", {
        "joint": "the most probable whole token of the mixture",
        "factored": "each factor's argmax of the per-factor marginals (the earlier behaviour; it can pair two "
                    "neighbours' factors into a token neither holds)",
        "best_neighbour": "as joint, but a copy takes the single most weighted neighbour's token, not the token "
                          "with the most weight summed over the neighbours holding it (which grows flat patches "
                          "in rollouts)"}),
    ("--sampled_tokens", "sampling (--temperature > 0) draws", {
        "joint": "a whole token from the mixture (an option, then for a new token the readout's factors)",
        "factored": "each factor on its own from the per-factor marginals (the earlier behaviour; it can pair two "
                    "neighbours' factors into a token neither holds)"}),
)


def add_token_choice_args(parser) -> None:
    """--greedy_tokens and --sampled_tokens of the scripts that decode with a dynamics model
    (STMaskGIT.set_greedy_tokens, STMaskGIT.set_joint_sampling)."""
    for flag, when, choices in TOKEN_CHOICES:
        described = "; ".join(f"{name}: {what}" for name, what in choices.items())
        parser.add_argument(flag, choices=tuple(choices), default=next(iter(choices)),
                            help=f"How {when} each token of a model with a copy head (copy_radius): {described}. "
                                 f"Models without a copy head decode the same either way.")


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
    """--stall_ratio of the scripts that generate futures (genie.inference.generate's stall rule)."""
    parser.add_argument("--stall_ratio", type=_share, default=None,
                        help="Decoding rule for free-running futures, off by default: once a generated frame changes "
                             "at most this fraction of what the prompt's frames change per step (the share of "
                             "tokens that differ from the frame before; e.g. 0.66), the window's future is taken to "
                             "have stopped moving and every later frame repeats that one. A small model's greedy "
                             "futures slow down and then decay in place; this holds them where they stopped. Needs "
                             "at least 2 prompt frames. Teacher-forced predictions are unaffected.")


def check_stall_ratio(parser, stall_ratio, num_prompt_frames: int) -> None:
    """Usage error when --stall_ratio is set but the prompt has fewer than the 2 frames its motion is measured on."""
    if stall_ratio is not None and num_prompt_frames < 2:
        parser.error(f"--stall_ratio compares generated frames with the prompt's motion: it needs --num_prompt_frames "
                     f">= 2, got {num_prompt_frames}")


def finite_float(text: str) -> float:
    """argparse type: a finite number (not nan or inf, which would otherwise surface as a traceback from deep inside
    torch, or as silently meaningless results)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def check_optimizer_args(parser, args, rates=("learning_rate",), betas=()) -> None:
    """parser.error unless every learning rate in `rates` (None: unset) is > 0, --weight_decay >= 0 and every
    momentum-like coefficient in `betas` is in [0, 1): the optimizers' own checks would stop with a traceback."""
    for name in rates:
        if getattr(args, name) is not None and getattr(args, name) <= 0:
            parser.error(f"--{name} must be > 0, got {getattr(args, name)}")
    if args.weight_decay < 0:
        parser.error(f"--weight_decay must be >= 0, got {args.weight_decay}")
    for name in betas:
        if not 0 <= getattr(args, name) < 1:
            parser.error(f"--{name} must be in [0, 1), got {getattr(args, name)}")


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def add_num_threads_arg(parser) -> None:
    parser.add_argument("--num_threads", type=non_negative_int, default=0,
                        help="CPU threads for torch (0: torch's default, one per core); 1 gives steadier, often "
                             "faster runs of small models on a busy shared machine, e.g. two runs side by side on "
                             "two cores")


def apply_cpu_settings(num_threads: int) -> None:
    """A script's process-wide CPU settings, applied at the start of its main(): torch's thread count (0: torch's
    default) and an allocator that keeps freed memory for the next step's tensors (common/allocator.py; glibc's
    defaults where the environment opts out)."""
    retain_freed_memory()
    if num_threads > 0:
        torch.set_num_threads(num_threads)


def add_hidden_alias(parser, option: str, dest: str, **kwargs) -> None:
    """An earlier spelling of an option (e.g. --adam_beta1 for --adam_beta_1): it keeps working but --help shows
    only the current one. Add it after the current option, whose default it leaves alone."""
    parser.add_argument(option, dest=dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)
