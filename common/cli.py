"""Command-line helpers shared by every script: the --device and --num_threads flags, and one logging set-up."""
import argparse
import logging
import math
import sys
from pathlib import Path
from typing import Callable, Optional

from common.device import NO_NATIVE_BF16, apply_cpu_settings, cpu_has_native_bf16, resolve_device  # noqa: F401
from common.errors import InputError, TrainingError, WriteError

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%H:%M:%S"


def setup_logging(level: int = logging.INFO) -> None:
    """The one log format of all scripts (stderr, so that stdout stays free for results such as JSON lines)."""
    logging.basicConfig(format=LOG_FORMAT, datefmt=LOG_DATE_FORMAT, level=level)


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


def add_hidden_alias(parser, option: str, dest: str, **kwargs) -> None:
    """An earlier spelling of an option (e.g. --adam_beta1 for --adam_beta_1): it keeps working but --help shows
    only the current one. Add it after the current option, whose default it leaves alone."""
    parser.add_argument(option, dest=dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)


def run_main(prog: str, main: Callable[[Optional[list]], Optional[int]], argv: Optional[list] = None) -> int:
    """Run a script's `main(argv)` and return its exit status; bad input ends it in one line on stderr,
    "<prog>: error: <message>", exit status 1, with no traceback: the project's `InputError`s (configs, checkpoints,
    datasets, mismatches), a disk that refused a write, a path that is missing, in the way or not permitted, and
    a training run that cannot go on.
    Anything else is a bug and keeps its traceback. Use as `sys.exit(run_main("train.py", main))`."""
    try:
        return main(argv) or 0
    except (InputError, WriteError, TrainingError, FileNotFoundError, FileExistsError, NotADirectoryError,
            IsADirectoryError, PermissionError) as e:
        print(f"{prog}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a count of steps, frames, workers, ...)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {value}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def existing_dir(text: str) -> Path:
    """argparse type: a directory that exists."""
    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {'not a directory' if path.exists() else 'no such directory'}")
    return path
