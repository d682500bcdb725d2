"""Learning-rate schedules as step -> factor of the peak rate (for torch.optim.lr_scheduler.LambdaLR)."""
import math

LR_SCHEDULES = ("constant", "constant_with_warmup", "linear", "cosine", "custom_cosine")


def lr_multiplier(kind: str, warmup: int, total: int):
    """step -> factor of the peak learning rate (Hugging Face semantics; custom_cosine as in the 1X script:
    linear warmup reaching 1 at step warmup - 1, then cosine decay to 10 % at `total`)."""
    if kind not in LR_SCHEDULES:
        raise ValueError(f"unknown learning-rate schedule {kind!r}; choose one of {LR_SCHEDULES}")

    def factor(step: int) -> float:
        if kind == "constant":
            return 1.0
        if kind == "custom_cosine":
            if step < warmup:
                return (step + 1) / warmup
            progress = (step - warmup) / max(1, total - warmup)
            return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))
        if step < warmup:
            return step / max(1, warmup)
        if kind == "constant_with_warmup":
            return 1.0
        progress = (step - warmup) / max(1, total - warmup)
        if kind == "linear":
            return max(0.0, 1.0 - progress)
        return max(0.0, 0.5 * (1 + math.cos(math.pi * progress)))  # cosine
    return factor
