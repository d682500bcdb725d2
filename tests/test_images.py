"""SSIM (common/images.py) against a per-pixel loop written from Wang et al. 2004, and its basic properties."""
import math

import numpy as np
import pytest
import torch

from common.images import ssim


def loop_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of one pair of uint8 (H, W, C) images, one window position and one channel at a time."""
    offsets = np.arange(11) - 5
    g = np.exp(-offsets ** 2 / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x_all, y_all = a.astype(np.float64) / 255, b.astype(np.float64) / 255
    H, W, C = a.shape
    values = []
    for c in range(C):
        for i in range(H - 10):
            for j in range(W - 10):
                x, y = x_all[i:i + 11, j:j + 11, c], y_all[i:i + 11, j:j + 11, c]
                mx, my = (w * x).sum(), (w * y).sum()
                vx, vy = (w * (x - mx) ** 2).sum(), (w * (y - my) ** 2).sum()
                cxy = (w * (x - mx) * (y - my)).sum()
                values.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    return float(np.mean(values))


def random_images(n=2, h=14, w=13, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8))


def test_ssim_matches_a_per_pixel_loop():
    a = random_images(seed=0)
    b = (a.int() + torch.from_numpy(np.random.default_rng(1).integers(-40, 41, a.shape))).clamp(0, 255).to(torch.uint8)
    got = ssim(a, b)
    assert got.shape == (2,)
    for i in range(2):
        assert got[i].item() == pytest.approx(loop_ssim(a[i].numpy(), b[i].numpy()), abs=1e-5)
    c = random_images(seed=2)  # independent noise: near 0
    assert abs(ssim(a, c)[0].item() - loop_ssim(a[0].numpy(), c[0].numpy())) < 1e-5


def test_ssim_identical_symmetric_and_lowered_by_a_brightness_shift():
    a, b = random_images(seed=3), random_images(seed=4)
    torch.testing.assert_close(ssim(a, a), torch.ones(2))
    torch.testing.assert_close(ssim(a, b), ssim(b, a))
    smooth = torch.linspace(40, 200, 32).view(1, 1, 32, 1).expand(1, 32, 32, 3).to(torch.uint8)
    scores = [ssim(smooth, (smooth.int() + shift).to(torch.uint8)).item() for shift in (0, 10, 40)]
    assert scores[0] == pytest.approx(1.0) and scores[0] > scores[1] > scores[2]
    assert scores[1] == pytest.approx(loop_ssim(smooth[0].numpy(), (smooth[0].int() + 10).to(torch.uint8).numpy()),
                                      abs=1e-5)
    assert not math.isnan(ssim(torch.zeros_like(a), torch.zeros_like(a))[0].item())  # flat images: 1, not 0/0


def test_ssim_rejects_small_or_mismatched_images():
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(random_images(h=8), random_images(h=8))
    with pytest.raises(ValueError, match="one shape"):
        ssim(random_images(h=14), random_images(h=15))
