"""Image metrics shared by the evaluator (decoded uint8 frames) and the latent action model (frames in [-1, 1])."""
import torch


def psnr(pred: torch.Tensor, target: torch.Tensor, value_range) -> torch.Tensor:
    """(N,) PSNR in dB of N images (any layout after the first dimension) whose pixels span value_range = (low,
    high), e.g. (0, 255) for uint8 frames or (-1, 1) for model inputs.

    pred is clamped to the range first (a decoder may overshoot it); the error is measured at [0, 1] scale and
    floored at 1e-10, so identical images give 100 dB.
    """
    low, high = value_range
    diff = (pred.float().clamp(low, high) - target.float()) / (high - low)
    mse_N = (diff ** 2).flatten(1).mean(dim=1)
    return -10.0 * torch.log10(mse_N.clamp_min(1e-10))
