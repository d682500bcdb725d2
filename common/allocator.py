"""The C allocator told to keep freed memory for reuse (glibc on Linux), so that a training step's large tensors do
not fault in fresh pages every step.

PyTorch's CPU tensors come from malloc. glibc serves an allocation above its mmap threshold (128 KiB at first,
raised on the fly up to 32 MiB) with a fresh mmap, and trims the heap top back to the kernel once more than twice
that threshold is free. Either way a tensor of a few MiB allocated again on the next step lands on pages the kernel
has to fault in and zero again: on the main command's training step 21,000-30,000 minor page faults per step, whose
removal makes the step 1.09x faster on a 2-core AVX-512 Xeon (`benchmarks/bench_allocator.py`; `bench_train.py`
prints the faults: under 350 per step with these settings). Setting the mmap threshold to glibc's ceiling and switching trimming off keeps
freed blocks in the heap, where the next step's tensors of the same sizes find them. Nothing numerical changes:
every tensor still gets its own 64-byte aligned buffer and every operation the same inputs.

The cost is memory: the heap keeps its peak size (about 7 % more resident memory on the sample world's training).
`GENIE_DEFAULT_MALLOC=1` in the environment keeps glibc's own settings.
"""
import ctypes
import os
import sys

OPT_OUT_ENV = "GENIE_DEFAULT_MALLOC"
# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# glibc refuses an mmap threshold above half its largest heap: 32 MiB on 64-bit systems
_MMAP_THRESHOLD_MAX = 32 * 2 ** 20
_NEVER_TRIM = 2 ** 31 - 1  # an int: mallopt takes one


def retain_freed_memory() -> bool:
    """Set glibc's mmap threshold to its ceiling and switch heap trimming off for this process; True where the
    settings took (glibc on Linux, no opt-out), False where the process keeps its allocator's defaults."""
    if os.environ.get(OPT_OUT_ENV, "") not in ("", "0") or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # The threshold first: a trim threshold set alone also pins the mmap threshold at its 128 KiB start, which
    # maps every larger tensor afresh (ten times the faults of the defaults).
    if not mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX):
        return False
    return bool(mallopt(_M_TRIM_THRESHOLD, _NEVER_TRIM))
