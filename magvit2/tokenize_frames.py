"""Frames (+ per-frame actions and segment ids) -> a token dataset in the 1X layout (docs/formats.md §1).

Inputs, in the order given:
- an .npz with `frames` (N, H, W, 3) uint8, optional `segment_ids` (N,) int (non-decreasing), optional action arrays
  `actions_<name>` (N, k) or (N,) and an optional scalar `hz`. Without segment_ids the file is one segment;
- a folder of images (png/jpg/jpeg/bmp/webp, natural sort order): one segment, no actions;
- a folder of .npz files: each file in natural sort order, as above (e.g. one episode per file).
Segment ids stay distinct across inputs: an input's ids are shifted, when needed, to start after the previous one's.
All inputs are checked (shapes, action names, hz) before anything is encoded.

    python -m magvit2.tokenize_frames episodes/ --tokenizer_ckpt data/magvit2.ckpt --output_dir data/my_robot
"""
import argparse
import logging
import re
import sys
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image
from tqdm import tqdm

from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, positive_float, positive_int,
                        resolve_device, run_main, setup_logging)
from common.errors import InputError
from data import TokenDatasetWriter
from magvit2.model import VQModel

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
ACTION_PREFIX = "actions_"
DEFAULT_HZ = 30


class TokenizeInputError(InputError):
    """An input file or folder that cannot be tokenized; the message names it."""


@dataclass
class Episode:
    """Frames (N, H, W, 3) uint8 (an array or a lazily sliced sequence), optional (N,) segment ids and
    name -> (N, k) actions. Built cheaply by `describe_input` (arrays loaded on first use)."""
    source: str
    num_frames: int
    frame_hw: Tuple[int, int]
    action_dims: Dict[str, int] = field(default_factory=dict)
    hz: Optional[float] = None
    frames: Optional[Sequence] = None
    segment_ids: Optional[np.ndarray] = None
    actions: Dict[str, np.ndarray] = field(default_factory=dict)


def _natural_key(path: Path):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


class ImageFolderFrames:
    """The images of a folder as a lazily loaded (N, H, W, 3) uint8 sequence, read one slice at a time."""

    def __init__(self, paths: List[Path], size_wh: Tuple[int, int]):
        self.paths, self.size_wh = paths, size_wh

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: slice) -> np.ndarray:
        frames = []
        for path in self.paths[index]:
            try:
                with Image.open(path) as im:
                    frame = np.asarray(im.convert("RGB"))
            except OSError as e:
                raise TokenizeInputError(f"{path}: cannot read image ({e})") from None
            if frame.shape[1::-1] != self.size_wh:
                raise TokenizeInputError(f"{path}: image size {frame.shape[1]}x{frame.shape[0]} differs from the "
                                         f"folder's first image {self.size_wh[0]}x{self.size_wh[1]}")
            frames.append(frame)
        return np.stack(frames)


def _npz_header(npz, key: str):
    """(shape, dtype) of one array of an .npz without loading it."""
    with npz.zip.open(f"{key}.npy") as f:
        version = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
    return shape, dtype


def _describe_npz(path: Path) -> Episode:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return _describe_open_npz(path, npz)
    except TokenizeInputError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, KeyError) as e:
        raise TokenizeInputError(f"{path}: cannot read as .npz ({e})") from None


def _describe_open_npz(path: Path, npz) -> Episode:
    if "frames" not in npz.files:
        raise TokenizeInputError(f"{path}: no 'frames' array (found {npz.files})")
    shape, dtype = _npz_header(npz, "frames")
    if dtype != np.uint8 or len(shape) != 4 or shape[-1] != 3:
        raise TokenizeInputError(f"{path}: 'frames' must be uint8 (N, H, W, 3), got {dtype} {shape}")
    n = shape[0]
    if "segment_ids" in npz.files:
        seg_shape, seg_dtype = _npz_header(npz, "segment_ids")
        if seg_shape != (n,) or not np.issubdtype(seg_dtype, np.integer):
            raise TokenizeInputError(f"{path}: 'segment_ids' must be integers of shape ({n},), got {seg_dtype} "
                                     f"{seg_shape}")
    action_dims = {}
    for key in npz.files:
        if key.startswith(ACTION_PREFIX):
            a_shape, a_dtype = _npz_header(npz, key)
            if len(a_shape) not in (1, 2) or a_shape[0] != n or 0 in a_shape or not np.issubdtype(a_dtype, np.number):
                raise TokenizeInputError(f"{path}: '{key}' must be numeric of shape ({n}, k) or ({n},), got "
                                         f"{a_dtype} {a_shape}")
            action_dims[key[len(ACTION_PREFIX):]] = a_shape[1] if len(a_shape) == 2 else 1
    hz = None
    if "hz" in npz.files:
        value = npz["hz"]
        if value.size != 1 or not np.issubdtype(value.dtype, np.number) or not float(value) > 0:
            raise TokenizeInputError(f"{path}: 'hz' must be one positive number, got {value!r}")
        hz = float(value)
    return Episode(str(path), n, tuple(shape[1:3]), action_dims, hz)


def _describe_image_folder(folder: Path, paths: List[Path]) -> Episode:
    try:
        with Image.open(paths[0]) as im:
            size_wh = im.size
    except OSError as e:
        raise TokenizeInputError(f"{paths[0]}: cannot read image ({e})") from None
    return Episode(str(folder), len(paths), (size_wh[1], size_wh[0]), frames=ImageFolderFrames(paths, size_wh))


def describe_inputs(inputs: Iterable) -> List[Episode]:
    """Expand .npz files, image folders and folders of .npz files into episodes (arrays not yet loaded)."""
    episodes = []
    for item in map(Path, inputs):
        if not item.exists():
            raise FileNotFoundError(f"input not found: {item}")
        if item.is_file():
            if item.suffix != ".npz":
                raise TokenizeInputError(f"{item}: expected an .npz file or a folder of images / .npz files")
            episodes.append(_describe_npz(item))
            continue
        npzs = sorted(item.glob("*.npz"), key=_natural_key)
        images = sorted((p for p in item.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS), key=_natural_key)
        if npzs and images:
            raise TokenizeInputError(f"{item}: holds both .npz files and images; pass them separately")
        if not npzs and not images:
            raise TokenizeInputError(f"{item}: no .npz files and no images ({', '.join(IMAGE_EXTENSIONS)})")
        episodes.extend([_describe_npz(p) for p in npzs] if npzs else [_describe_image_folder(item, images)])
    return episodes


def _load(episode: Episode) -> Episode:
    """Load an .npz episode's arrays (image folders stay lazy)."""
    if episode.frames is not None:
        return episode
    with np.load(episode.source, allow_pickle=False) as npz:
        segment_ids = npz["segment_ids"] if "segment_ids" in npz.files else None
        if segment_ids is not None and (np.diff(segment_ids) < 0).any():
            raise TokenizeInputError(f"{episode.source}: 'segment_ids' must be non-decreasing")
        actions = {name: npz[ACTION_PREFIX + name].reshape(episode.num_frames, -1) for name in episode.action_dims}
        return Episode(episode.source, episode.num_frames, episode.frame_hw, episode.action_dims, episode.hz,
                       npz["frames"], segment_ids, actions)


def resize_frames(frames_NHWC: np.ndarray, image_size: Optional[int]) -> np.ndarray:
    """Center-crop to a square and resize to image_size x image_size (None: unchanged)."""
    if image_size is None:
        return frames_NHWC
    out = []
    for frame in frames_NHWC:
        h, w = frame.shape[:2]
        side = min(h, w)
        top, left = (h - side) // 2, (w - side) // 2
        im = Image.fromarray(frame[top:top + side, left:left + side])
        out.append(np.asarray(im.resize((image_size, image_size), Image.Resampling.BICUBIC)))
    return np.stack(out)


def _grid_side(episode: Episode, model: VQModel, image_size: Optional[int]) -> int:
    """The token grid side for an episode's frames; a clear error for frames the tokenizer cannot take."""
    h, w = episode.frame_hw
    f = model.config.downsample_factor
    if image_size is None and h != w:
        raise TokenizeInputError(f"{episode.source}: frames are {w}x{h}, not square; pass --image_size to "
                                 f"center-crop and resize them")
    side = image_size if image_size is not None else h
    if side % f:
        raise TokenizeInputError(f"{episode.source}: frame side {side} is not divisible by the tokenizer's "
                                 f"downsample factor {f}; pass --image_size (e.g. {model.config.resolution})")
    return side // f


def _check_consistent(episodes: List[Episode], model: VQModel,
                      image_size: Optional[int]) -> Tuple[int, Optional[float]]:
    """Same token grid and action streams in every input, one hz. Returns (grid side, hz found or None)."""
    if not episodes:
        raise TokenizeInputError("no inputs to tokenize")
    first = episodes[0]
    grid = _grid_side(first, model, image_size)
    hz_values = {e.hz for e in episodes if e.hz is not None}
    if len(hz_values) > 1:
        raise TokenizeInputError(f"inputs disagree on hz ({sorted(hz_values)}); pass --hz to set it")
    for episode in episodes:
        if _grid_side(episode, model, image_size) != grid:
            raise TokenizeInputError(f"{episode.source}: frames {episode.frame_hw} give another token grid than "
                                     f"{first.source} {first.frame_hw}; pass --image_size to make them equal")
        if episode.action_dims != first.action_dims:
            raise TokenizeInputError(f"{episode.source}: actions {episode.action_dims} differ from those of "
                                     f"{first.source} {first.action_dims} (name -> dim)")
    side = grid * model.config.downsample_factor
    if side != model.config.resolution:
        logger.warning("frames are encoded at %dx%d but the tokenizer was configured for %dx%d", side, side,
                       model.config.resolution, model.config.resolution)
    return grid, (hz_values.pop() if hz_values else None)


def tokenize_episodes(model: VQModel, episodes: List[Episode], output_dir, tokenizer_ckpt: str,
                      hz: Optional[float] = None, image_size: Optional[int] = None, batch_size: int = 32,
                      overwrite: bool = False, progress: bool = True) -> Path:
    """Encode episodes (from `describe_inputs`, or in-memory Episode objects) into a token dataset at output_dir.

    hz: frame rate for metadata (default: the inputs' hz, else 30). tokenizer_ckpt is recorded in metadata.
    """
    grid, hz_found = _check_consistent(episodes, model, image_size)
    hz = hz if hz is not None else (hz_found if hz_found is not None else DEFAULT_HZ)
    config = model.config
    metadata = {"vocab_size": config.codebook_size, "hz": hz, "tokenizer_ckpt": str(tokenizer_ckpt),
                "token_dtype": "uint32" if config.z_channels <= 32 else "uint64"}
    next_segment = 0
    with TokenDatasetWriter(output_dir, grid, metadata=metadata, overwrite=overwrite) as writer, \
            tqdm(total=sum(e.num_frames for e in episodes), unit="frame", desc="tokenizing",
                 disable=not progress) as bar:
        for episode in map(_load, episodes):
            if episode.segment_ids is None:
                segment_ids = np.full(episode.num_frames, next_segment, dtype=np.int64)
            else:
                segment_ids = np.asarray(episode.segment_ids, dtype=np.int64)
                if len(segment_ids):
                    segment_ids = segment_ids + max(0, next_segment - int(segment_ids[0]))
            for start in range(0, episode.num_frames, batch_size):
                stop = min(start + batch_size, episode.num_frames)
                frames = resize_frames(np.asarray(episode.frames[start:stop]), image_size)
                tokens = model.images_to_tokens(frames, batch_size=batch_size)
                actions = {name: values[start:stop] for name, values in episode.actions.items()}
                writer.append(tokens, segment_ids[start:stop], actions)
                bar.update(stop - start)
            if episode.num_frames:
                next_segment = int(segment_ids[-1]) + 1
    return Path(output_dir)


def tokenize_frames(model: VQModel, frames_NHWC: np.ndarray, output_dir, tokenizer_ckpt: str,
                    segment_ids: Optional[np.ndarray] = None, actions: Optional[Dict[str, np.ndarray]] = None,
                    hz: float = DEFAULT_HZ, **kwargs) -> Path:
    """In-memory variant: frames (N, H, W, 3) uint8, segment_ids (N,), actions name -> (N, k). kwargs as
    tokenize_episodes (image_size, batch_size, overwrite, progress)."""
    frames_NHWC = np.asarray(frames_NHWC)
    if frames_NHWC.dtype != np.uint8 or frames_NHWC.ndim != 4 or frames_NHWC.shape[-1] != 3:
        raise TokenizeInputError(f"frames must be uint8 (N, H, W, 3), got {frames_NHWC.dtype} {frames_NHWC.shape}")
    n = len(frames_NHWC)
    actions = {name: np.asarray(v).reshape(n, -1) for name, v in (actions or {}).items()}
    episode = Episode("frames", n, frames_NHWC.shape[1:3], {k: v.shape[1] for k, v in actions.items()}, hz,
                      frames_NHWC, segment_ids, actions)
    return tokenize_episodes(model, [episode], output_dir, tokenizer_ckpt, hz=hz, **kwargs)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("inputs", nargs="+",
                        help=".npz files (frames, optional segment_ids, actions_<name>, hz), folders of images "
                             "(one segment each) or folders of .npz files (one episode per file)")
    parser.add_argument("--tokenizer_ckpt", required=True,
                        help="tokenizer checkpoint: a directory (config.json + model.safetensors) or a published "
                             "Lightning .ckpt such as data/magvit2.ckpt; recorded in the dataset's metadata")
    parser.add_argument("--output_dir", required=True, help="token dataset directory to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset at --output_dir")
    parser.add_argument("--batch_size", type=positive_int, default=32, help="frames encoded per forward pass")
    add_device_arg(parser, help="torch device for the encoder: auto (cuda when available, else cpu), cpu, cuda or "
                                "cuda:N")
    add_num_threads_arg(parser)
    parser.add_argument("--hz", type=positive_float, default=None,
                        help=f"frame rate written to metadata (default: the inputs' hz, else {DEFAULT_HZ})")
    parser.add_argument("--image_size", type=positive_int, default=None,
                        help="center-crop frames to a square and resize them to this side before encoding "
                             "(default: frames must already be square, with a side divisible by the tokenizer's "
                             "downsample factor)")
    parser.add_argument("--no_ema", action="store_true", help="use the raw instead of the EMA weights of a .ckpt")
    parser.add_argument("--allow_unsafe_pickle", action="store_true",
                        help="let torch.load run code from a .ckpt that weights_only loading refuses "
                             "(trusted files only)")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    setup_logging()
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    episodes = describe_inputs(args.inputs)
    output_dir = Path(args.output_dir)
    if output_dir.exists() and not args.overwrite and (not output_dir.is_dir() or any(output_dir.iterdir())):
        raise TokenizeInputError(f"{output_dir} already exists; pass --overwrite to replace it")
    model = VQModel.from_checkpoint(args.tokenizer_ckpt, use_ema=not args.no_ema,
                                    allow_unsafe_pickle=args.allow_unsafe_pickle,
                                    map_location=resolve_device(args.device))
    out = tokenize_episodes(model.eval(), episodes, output_dir, args.tokenizer_ckpt, hz=args.hz,
                            image_size=args.image_size, batch_size=args.batch_size, overwrite=args.overwrite)
    logger.info("wrote %d frames to %s", sum(e.num_frames for e in episodes), out)


if __name__ == "__main__":
    sys.exit(run_main("magvit2.tokenize_frames", main))
