"""torch.compile for training: the whole model on CUDA, the transformer blocks on the CPU.

On the CPU inductor writes C++ kernels, and for the token bookkeeping around the transformer (factorized ids, the
pointer's sources and masks) torch 2.13's code generator emits C++ that does not compile (mixed int64 and float
vector masks), so a whole-model compile stops at the first step. The blocks (float math only) compile, and they are
where fusing pays: attention, rotary positions, GELU, layer norms. They are compiled in place, so parameter names
and checkpoints are the same as without compiling.
"""
import shutil

import torch

from common.errors import TrainingError

# C++ compilers that inductor's CPU code generator can use
CPU_COMPILERS = ("g++", "c++", "clang++")


def compile_for_training(wrapped, model, device: torch.device):
    """Compile `model` (an STMaskGIT; `wrapped`: the same model as training calls it, e.g. DDP-wrapped) for
    `device`; returns what training should call."""
    if device.type != "cpu":
        return torch.compile(wrapped)
    if not any(shutil.which(cxx) for cxx in CPU_COMPILERS):
        raise TrainingError(f"--compile on the CPU needs a C++ compiler on the PATH ({' or '.join(CPU_COMPILERS)}; "
                            f"e.g. apt-get install g++), none found; train without --compile")
    for block in model.decoder.layers:
        block.compile()
    return wrapped
