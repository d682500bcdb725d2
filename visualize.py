#!/usr/bin/env python3
"""Decode a token directory (video.bin + metadata.json) with the MAGVIT2 tokenizer into a GIF and a comic strip.

- Generated token dirs (metadata has `num_prompt_frames` P and `window_size` W; every example is 2W - P frames,
  `prompt | predictions | ground truth`): a GIF showing the model's frames ("Prompt" / "Generated") beside the
  ground truth ("Prompt" / "Ground truth"), one row per example, and a comic PNG with two rows per example
  (prompt + predictions above, prompt + ground truth below). --offset / --stride / --max_examples pick examples.
- Plain datasets: a GIF of frames offset, offset + stride, ... (at most --max_images).
Optional per-frame text labels are drawn under each frame: --labels FILE, --label_action NAME (the values of the
token dir's actions/NAME.bin, e.g. the latent actions written by lam.label), or `frame_labels`
(a list or a function frame index -> text) in code.

    python visualize.py --token_dir data/genie_generated
"""
import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Union

import numpy as np
from matplotlib.figure import Figure
from PIL import Image, ImageDraw, ImageFont

from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, non_negative_int, positive_float,
                        positive_int, resolve_device, run_main, setup_logging)
from common.errors import InputError
from common.files import atomic_file
from data import RawTokenDataset
from magvit2 import VQModel

logger = logging.getLogger(__name__)

DEFAULT_TOKENIZER_CKPT = "data/magvit2.ckpt"
CAPTION_HEIGHT = 36
LABEL_HEIGHT = 24
MIN_DISPLAY_SIDE = 128
MAX_LABEL_VALUES = 4

FrameLabels = Union[Sequence[str], Callable[[int], str]]  # frame index in video.bin -> text


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--token_dir", default="data/genie_generated",
                        help="directory with video.bin + metadata.json (a dataset or generated tokens)")
    parser.add_argument("--output_dir", default=None, help="where the GIF and comic go (default: --token_dir)")
    parser.add_argument("--offset", type=non_negative_int, default=0,
                        help="first frame (plain dataset) or first example (generated dir) to show")
    parser.add_argument("--stride", type=positive_int, default=1, help="step between shown frames / examples")
    parser.add_argument("--fps", type=positive_float, default=2, help="GIF frames per second")
    parser.add_argument("--max_images", type=positive_int, default=None,
                        help="plain datasets: at most this many frames (default: all from --offset on)")
    parser.add_argument("--max_examples", type=positive_int, default=4,
                        help="generated dirs: at most this many examples")
    parser.add_argument("--disable_comic", action="store_true", help="do not write the comic PNG (generated dirs)")
    parser.add_argument("--tokenizer_ckpt", default=None,
                        help=f"tokenizer checkpoint (directory or .ckpt); default: the token dir's metadata "
                             f"`tokenizer_ckpt` if that exists, else {DEFAULT_TOKENIZER_CKPT}")
    labels = parser.add_mutually_exclusive_group()
    labels.add_argument("--labels", default=None,
                        help="per-frame text labels drawn under the frames: a .json list of strings or a text file "
                             "with one line per frame of video.bin")
    labels.add_argument("--label_action", default=None,
                        help="label each frame with its values of the action stream actions/<NAME>.bin of the token "
                             "dir (e.g. latent_action)")
    add_device_arg(parser, help="torch device for decoding: auto (cuda when available, else cpu), cpu, cuda or cuda:N")
    add_num_threads_arg(parser)
    parser.add_argument("--batch_size", type=positive_int, default=16, help="frames decoded per forward pass")
    parser.add_argument("--allow_unsafe_pickle", action="store_true",
                        help="let torch.load run code from a .ckpt that weights_only loading refuses "
                             "(trusted files only)")
    return parser.parse_args(argv)


def resolve_tokenizer_ckpt(explicit: Optional[str], metadata: dict) -> Path:
    """--tokenizer_ckpt, else the metadata's `tokenizer_ckpt` if it exists, else data/magvit2.ckpt."""
    if explicit is not None:
        if not Path(explicit).exists():
            raise FileNotFoundError(f"--tokenizer_ckpt {explicit} not found")
        return Path(explicit)
    tried = []
    if metadata.get("tokenizer_ckpt"):
        tried.append(f"metadata tokenizer_ckpt {metadata['tokenizer_ckpt']}")
        if Path(metadata["tokenizer_ckpt"]).exists():
            return Path(metadata["tokenizer_ckpt"])
    tried.append(f"the default {DEFAULT_TOKENIZER_CKPT}")
    if Path(DEFAULT_TOKENIZER_CKPT).exists():
        if len(tried) > 1:
            logger.warning("%s not found; decoding with %s", tried[0], DEFAULT_TOKENIZER_CKPT)
        return Path(DEFAULT_TOKENIZER_CKPT)
    raise FileNotFoundError(f"no tokenizer checkpoint found (tried {' and '.join(tried)}); pass --tokenizer_ckpt "
                            f"(a tokenizer directory or .ckpt)")


def load_labels(path, num_images: int) -> List[str]:
    """Per-frame labels from a .json list or a text file (one line per frame); must cover every frame."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--labels file not found: {path}")
    if path.suffix == ".json":
        try:
            labels = json.loads(path.read_text())
        except ValueError as e:
            raise InputError(f"{path}: not valid JSON ({e})") from None
        if not isinstance(labels, list):
            raise InputError(f"{path}: expected a JSON list of labels, got {type(labels).__name__}")
        labels = [str(label) for label in labels]
    else:
        labels = path.read_text().splitlines()
    if len(labels) != num_images:
        raise InputError(f"{path}: {len(labels)} labels but the token dir has {num_images} frames")
    return labels


def action_labels(dataset: RawTokenDataset, name: str) -> Callable[[int], str]:
    """Frame index -> 'name v1 v2 ...' from the token dir's actions/<name>.bin (read lazily)."""
    if name not in dataset.actions:
        raise InputError(f"{dataset.data_dir / 'actions' / (name + '.bin')} not found; action streams there: "
                         f"{dataset.action_names or 'none'}")
    values = dataset.actions[name]

    def label(index: int) -> str:
        row = [float(v) for v in values[index]]
        text = " ".join(str(int(v)) if v.is_integer() else f"{v:.2g}" for v in row[:MAX_LABEL_VALUES])
        return f"{name} {text}" + (" ..." if len(row) > MAX_LABEL_VALUES else "")

    return label


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow built without FreeType: fixed-size bitmap font
        return ImageFont.load_default()


def add_text_strip(image: Image.Image, text: str, height: int, on_top: bool) -> Image.Image:
    """A white strip with centered text above (caption) or below (label) the image; the font shrinks to fit."""
    out = Image.new("RGB", (image.width, image.height + height), "white")
    out.paste(image, (0, height if on_top else 0))
    draw = ImageDraw.Draw(out)
    size = int(height * 0.6)
    font = _font(size)
    while draw.textbbox((0, 0), text, font=font)[2] > image.width - 4 and size > 6:
        size -= 1
        font = _font(size)
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    y0 = 0 if on_top else image.height
    draw.text(((image.width - (right - left)) / 2 - left, y0 + (height - (bottom - top)) / 2 - top), text,
              fill="black", font=font)
    return out


def display_scale(side: int) -> int:
    """Integer nearest-neighbour zoom so that small frames (e.g. 64x64) are shown at least MIN_DISPLAY_SIDE wide."""
    return max(1, -(-MIN_DISPLAY_SIDE // side))


def frame_image(pixels_HWC: np.ndarray, caption: Optional[str] = None, label: Optional[str] = None) -> Image.Image:
    """A decoded frame, zoomed by display_scale, with an optional caption above and label below."""
    image = Image.fromarray(pixels_HWC)
    scale = display_scale(min(image.size))
    if scale > 1:
        image = image.resize((image.width * scale, image.height * scale), Image.Resampling.NEAREST)
    if caption is not None:
        image = add_text_strip(image, caption, CAPTION_HEIGHT, on_top=True)
    if label is not None:
        image = add_text_strip(image, label, LABEL_HEIGHT, on_top=False)
    return image


def grid_image(rows: Sequence[Sequence[Image.Image]]) -> Image.Image:
    """Paste equally sized images into a grid."""
    w, h = rows[0][0].size
    out = Image.new("RGB", (w * max(len(r) for r in rows), h * len(rows)), "white")
    for i, row in enumerate(rows):
        for j, image in enumerate(row):
            out.paste(image, (j * w, i * h))
    return out


def save_gif(frames: Sequence[Image.Image], path: Path, fps: float) -> None:
    """Write an animated GIF atomically (temp file + rename); a full disk raises WriteError."""
    atomic_file(path, lambda tmp: frames[0].save(tmp, format="GIF", save_all=True, append_images=list(frames[1:]),
                                                 duration=round(1000 / fps), loop=0), "the GIF")


def save_comic(panels: Sequence[Sequence[tuple]], path: Path) -> None:
    """panels: rows of (pixels_HWC, title, label or None). Written atomically as a PNG with matplotlib; a full
    disk raises WriteError."""
    nrows, ncols = len(panels), max(len(r) for r in panels)
    fig = Figure(figsize=(2.2 * ncols, 2.4 * nrows))
    axs = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axs.flat:
        ax.axis("off")
    for i, row in enumerate(panels):
        for j, (pixels, title, label) in enumerate(row):
            ax = axs[i, j]
            ax.imshow(pixels)
            ax.set_title(title, fontsize=9)
            if label is not None:
                ax.text(0.5, -0.04, label, transform=ax.transAxes, ha="center", va="top", fontsize=7)
    atomic_file(path, lambda tmp: fig.savefig(tmp, format="png", bbox_inches="tight"), "the comic")


def _label(labels: Optional[FrameLabels], index: int) -> Optional[str]:
    if labels is None:
        return None
    return labels(int(index)) if callable(labels) else labels[index]


def visualize_generated(model: VQModel, tokens: np.ndarray, metadata: dict, out_dir: Path, offset: int = 0,
                        stride: int = 1, max_examples: int = 4, fps: float = 2, comic: bool = True,
                        frame_labels: Optional[FrameLabels] = None, batch_size: int = 16) -> List[Path]:
    """GIF (+ comic) of generated examples. tokens: (N, s, s), N a multiple of 2W - P. Returns the files written."""
    P, W = metadata["num_prompt_frames"], metadata["window_size"]
    example_len = 2 * W - P
    if not (isinstance(P, int) and isinstance(W, int) and 1 <= P < W):
        raise InputError(f"metadata num_prompt_frames={P!r}, window_size={W!r}: need integers with "
                         f"1 <= num_prompt_frames < window_size")
    if len(tokens) % example_len:
        raise InputError(f"{len(tokens)} frames is not a multiple of 2 * window_size - num_prompt_frames = "
                         f"{example_len} (prompt | predictions | ground truth per example)")
    examples = list(range(offset, len(tokens) // example_len, stride))[:max_examples]
    if not examples:
        raise InputError(f"--offset {offset} is past the last example ({len(tokens) // example_len} examples)")
    frame_ids = np.concatenate([np.arange(e * example_len, (e + 1) * example_len) for e in examples])
    pixels = model.tokens_to_images(np.asarray(tokens[frame_ids]), batch_size=batch_size)
    pixels = pixels.reshape(len(examples), example_len, *pixels.shape[1:])

    def generated(e, t):  # (pixels, caption, label) of the model's frame t: prompt or prediction
        return pixels[e, t], "Prompt" if t < P else "Generated", _label(frame_labels, frame_ids[e * example_len + t])

    def truth(e, t):  # ground truth frame t: the prompt, then the stored ground truth after the predictions
        k = t if t < P else W + t - P
        return pixels[e, k], "Prompt" if t < P else "Ground truth", _label(frame_labels, frame_ids[e * example_len + k])

    gif_frames = []
    for t in range(W):
        rows = [[frame_image(*generated(e, t)), frame_image(*truth(e, t))] for e in range(len(examples))]
        gif_frames.append(grid_image(rows))
    written = [out_dir / f"generated_offset{offset}.gif"]
    save_gif(gif_frames, written[0], fps)
    if comic:
        panels = []
        for e in range(len(examples)):
            panels.append([generated(e, t) for t in range(W)])
            panels.append([truth(e, t) for t in range(W)])
        panels = [[(p, "Prediction" if c == "Generated" else c, lab) for p, c, lab in row] for row in panels]
        written.append(out_dir / f"generated_comic_offset{offset}.png")
        save_comic(panels, written[1])
    return written


def visualize_frames(model: VQModel, tokens: np.ndarray, out_dir: Path, offset: int = 0, stride: int = 1,
                     max_images: Optional[int] = None, fps: float = 2, frame_labels: Optional[FrameLabels] = None,
                     batch_size: int = 16) -> List[Path]:
    """Plain GIF of frames offset, offset + stride, ... of tokens (N, s, s). Returns the files written."""
    frame_ids = np.arange(offset, len(tokens), stride)[:max_images]
    if not len(frame_ids):
        raise InputError(f"--offset {offset} is past the last frame ({len(tokens)} frames)")
    if len(frame_ids) > 1000:
        logger.warning("decoding %d frames into one GIF; --max_images limits that", len(frame_ids))
    pixels = model.tokens_to_images(tokens[offset::stride][:len(frame_ids)], batch_size=batch_size)
    frames = [frame_image(p, label=_label(frame_labels, i)) for p, i in zip(pixels, frame_ids)]
    path = out_dir / f"generated_offset{offset}.gif"
    save_gif(frames, path, fps)
    return [path]


def main(argv=None) -> None:
    setup_logging()
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    dataset = RawTokenDataset(args.token_dir, window_size=1, filter_interrupts=False)
    tokens, metadata = dataset.data, dataset.metadata
    labels = load_labels(args.labels, len(tokens)) if args.labels else None
    if args.label_action:
        labels = action_labels(dataset, args.label_action)
    ckpt = resolve_tokenizer_ckpt(args.tokenizer_ckpt, metadata)
    model = VQModel.from_checkpoint(ckpt, allow_unsafe_pickle=args.allow_unsafe_pickle,
                                    map_location=resolve_device(args.device)).eval()
    out_dir = Path(args.output_dir if args.output_dir is not None else args.token_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if all(key in metadata for key in ("num_prompt_frames", "window_size")):
        written = visualize_generated(model, tokens, metadata, out_dir, args.offset, args.stride,
                                      args.max_examples, args.fps, not args.disable_comic, labels, args.batch_size)
    else:
        if not args.disable_comic:
            logger.info("%s is a plain dataset (no num_prompt_frames / window_size): GIF only, no comic",
                        args.token_dir)
        written = visualize_frames(model, tokens, out_dir, args.offset, args.stride, args.max_images, args.fps,
                                   labels, args.batch_size)
    for path in written:
        print(f"Saved to {path}")


if __name__ == "__main__":
    sys.exit(run_main("visualize.py", main))
