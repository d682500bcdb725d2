"""The device and CPU settings of a process: which torch device a name means, native bf16, threads and allocator."""
from pathlib import Path

import torch

from common.allocator import retain_freed_memory


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


def apply_cpu_settings(num_threads: int) -> None:
    """A script's process-wide CPU settings, applied at the start of its main(): torch's thread count (0: torch's
    default) and an allocator that keeps freed memory for the next step's tensors (common/allocator.py; glibc's
    defaults where the environment opts out)."""
    retain_freed_memory()
    if num_threads > 0:
        torch.set_num_threads(num_threads)
