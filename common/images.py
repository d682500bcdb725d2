"""Image metrics: PSNR, shared by the evaluator (decoded uint8 frames) and the latent action model (frames in
[-1, 1]); SSIM and sharpness of uint8 frames; KID between two sets of feature rows (the play protocol, the
tokenizer's score)."""
import torch
import torch.nn.functional as F


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


SSIM_WINDOW = 11  # Gaussian window of Wang et al. 2004: 11x11, sigma 1.5
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _gaussian_filter(x_BHW: torch.Tensor, kernel_K: torch.Tensor) -> torch.Tensor:
    """Weighted means over every 11x11 window fully inside the images ('valid'): (B, H, W) -> (B, H-10, W-10).
    The 2-D Gaussian is the outer product of kernel_K with itself, so it runs as two 1-D passes."""
    K = len(kernel_K)
    x_B1HW = x_BHW.unsqueeze(1)
    x_B1HW = F.conv2d(x_B1HW, kernel_K.view(1, 1, K, 1))
    return F.conv2d(x_B1HW, kernel_K.view(1, 1, 1, K)).squeeze(1)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,) structural similarity of N pairs of uint8 RGB images (N, H, W, 3), H and W >= 11.

    The standard SSIM (Wang et al. 2004): pixels scaled to [0, 1] (data range L = 1, C1 = (0.01 L)^2,
    C2 = (0.03 L)^2), local means, variances and covariance weighted by an 11x11 Gaussian window with sigma 1.5
    (normalized to sum 1), the SSIM map over every window position fully inside the image (no padding, as the
    authors' reference code), averaged over positions and then over the 3 colour channels (per-channel SSIM, not
    grayscale). Symmetric in a and b; 1 for identical images. Computed in float64: the variances are differences
    of nearly equal means, which float32 would blur in flat regions.
    """
    if a.shape != b.shape or a.dim() != 4:
        raise ValueError(f"ssim needs two (N, H, W, C) batches of one shape, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")
    N, H, W, C = a.shape
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {H}x{W}")
    offsets_K = torch.arange(SSIM_WINDOW, dtype=torch.float64, device=a.device) - (SSIM_WINDOW - 1) / 2
    kernel_K = torch.exp(-offsets_K ** 2 / (2 * SSIM_SIGMA ** 2))
    kernel_K = kernel_K / kernel_K.sum()
    # one image per (pair, channel)
    x_BHW = a.permute(0, 3, 1, 2).reshape(N * C, H, W).double() / 255
    y_BHW = b.permute(0, 3, 1, 2).reshape(N * C, H, W).double() / 255
    mu_x, mu_y = _gaussian_filter(x_BHW, kernel_K), _gaussian_filter(y_BHW, kernel_K)
    var_x = _gaussian_filter(x_BHW * x_BHW, kernel_K) - mu_x ** 2
    var_y = _gaussian_filter(y_BHW * y_BHW, kernel_K) - mu_y ** 2
    cov_xy = _gaussian_filter(x_BHW * y_BHW, kernel_K) - mu_x * mu_y
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    map_Bhw = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return map_Bhw.reshape(N, C, -1).mean(dim=(1, 2)).float()


def sharpness(images_NHW3: torch.Tensor) -> torch.Tensor:
    """uint8 images (N, H, W, 3) -> (N,) mean absolute Laplacian of the grey image (0-255 scale), inside the border."""
    grey_N1HW = images_NHW3.float().mean(dim=-1, keepdim=True).permute(0, 3, 1, 2)
    kernel = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]).view(1, 1, 3, 3)
    return F.conv2d(grey_N1HW, kernel.to(grey_N1HW.device)).abs().mean(dim=(1, 2, 3))


def kid(features_a: torch.Tensor, features_b: torch.Tensor) -> float:
    """Kernel inception distance between two sets of feature rows (n, d) and (m, d), n, m >= 2: the unbiased MMD^2
    with the kernel k(x, y) = (x.y / d + 1)^3. Its expectation is 0 for two samples of the same distribution, so a
    small set can come out slightly negative."""
    a, b = features_a.double(), features_b.double()
    n, m, d = len(a), len(b), a.shape[1]
    if n < 2 or m < 2:
        raise ValueError(f"kid needs at least 2 rows in each set, got {n} and {m}")
    k_aa, k_bb, k_ab = ((x @ y.T / d + 1) ** 3 for x, y in ((a, a), (b, b), (a, b)))
    same_a = (k_aa.sum() - k_aa.diagonal().sum()) / (n * (n - 1))
    same_b = (k_bb.sum() - k_bb.diagonal().sum()) / (m * (m - 1))
    return float(same_a + same_b - 2 * k_ab.mean())
