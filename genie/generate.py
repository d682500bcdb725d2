"""Generate future frames (as tokens) with a GENIE checkpoint from validation windows.

    python genie/generate.py --checkpoint_dir data/genie_model/final_checkpt --output_dir data/genie_generated
    python visualize.py --token_dir data/genie_generated

For each of `--num_examples` windows starting at dataset index `--example_ind`, the first `--num_prompt_frames`
frames are the prompt and the remaining `window_size - num_prompt_frames` frames are predicted with MaskGIT
(autoregressively in time, or with `--teacher_force_time` from the ground truth of all earlier frames).
The output directory uses the token dataset layout (video.bin + metadata.json, written atomically); each example
contributes `2 * window_size - num_prompt_frames` frames, ordered prompt | predictions | ground truth.
"""
import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from tqdm.auto import tqdm

from data import RawTokenDataset, TokenDatasetError, write_token_dataset
from genie.config import ConfigError
from genie.st_mask_git import CheckpointError, STMaskGIT

logger = logging.getLogger("genie.generate")


class GenerationError(ValueError):
    """Arguments, checkpoint and data that do not fit together."""


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="Generate future frames (tokens) from a GENIE checkpoint.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--val_data_dir", default="data/sample/val" if Path("data/sample/val").exists() else "data/val_v1.1",
                   help="Token dataset directory whose windows provide the prompts and the ground truth.")
    p.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt",
                   help="Hugging Face checkpoint directory (config.json + model.safetensors).")
    p.add_argument("--output_dir", default="data/genie_generated",
                   help="Where video.bin + metadata.json are written (replaced if it exists).")
    p.add_argument("--num_prompt_frames", type=int, default=8, help="Ground-truth frames given as context.")
    p.add_argument("--window_size", type=int, default=16,
                   help="Frames per window (must equal the checkpoint's T); window_size - num_prompt_frames are "
                        "generated.")
    p.add_argument("--stride", type=int, default=15, help="Frames between consecutive frames of a window.")
    p.add_argument("--example_ind", type=int, default=0, help="Dataset index of the first window to generate on.")
    p.add_argument("--num_examples", type=int, default=1, help="Consecutive windows to generate on.")
    p.add_argument("--batch_size", type=int, default=8, help="Windows generated at once.")
    p.add_argument("--teacher_force_time", action="store_true",
                   help="Predict frame t from the ground truth of frames < t (as the challenge metrics do) instead "
                        "of from the model's own earlier predictions.")
    p.add_argument("--maskgit_steps", type=int, default=2, help="MaskGIT decoding steps per frame.")
    p.add_argument("--temperature", type=float, default=0.0, help="Sampling temperature; 0 samples greedily.")
    p.add_argument("--unmask_mode", default="random", choices=("random", "greedy"),
                   help="Which tokens each MaskGIT step reveals: random (published default) or most confident.")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu).")
    p.add_argument("--seed", type=int, default=0, help="Seed of the sampling randomness.")
    args = p.parse_args(argv)
    for name in ("window_size", "stride", "num_examples", "batch_size", "maskgit_steps"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not 1 <= args.num_prompt_frames < args.window_size:
        p.error(f"--num_prompt_frames must be in [1, window_size={args.window_size}), got {args.num_prompt_frames}")
    if args.example_ind < 0 or args.temperature < 0:
        p.error("--example_ind and --temperature must be >= 0")
    return args


def check_compatible(model: STMaskGIT, dataset: RawTokenDataset, args) -> None:
    """Clear errors when the checkpoint, the data and the arguments disagree on shapes or vocabulary."""
    config, meta = model.config, dataset.metadata
    where = dataset.data_dir / "metadata.json"
    if args.window_size != config.T:
        raise GenerationError(f"--window_size {args.window_size} differs from the checkpoint's T={config.T} "
                              f"({args.checkpoint_dir}/config.json)")
    if meta["s"] ** 2 != config.S:
        raise GenerationError(f"{where}: frames are {meta['s']}x{meta['s']} tokens but the checkpoint "
                              f"{args.checkpoint_dir} expects S={config.S} tokens per frame")
    if meta["vocab_size"] != config.image_vocab_size:
        raise GenerationError(f"{where}: vocab_size {meta['vocab_size']} differs from the checkpoint's "
                              f"image_vocab_size {config.image_vocab_size} ({args.checkpoint_dir})")
    last = args.example_ind + args.num_examples - 1
    if last >= len(dataset):
        raise GenerationError(f"{dataset.data_dir}: examples {args.example_ind}..{last} requested but the dataset has "
                              f"{len(dataset)} windows of {args.window_size} frames with stride {args.stride}")


def load_windows(dataset: RawTokenDataset, indices, s: int) -> torch.Tensor:
    """Ground-truth windows (B, T, H, W) int64."""
    windows = [dataset[i]["input_ids"] for i in indices]
    return rearrange(torch.stack(windows), "b (t h w) -> b t h w", t=dataset.window_size, h=s, w=s)


@torch.no_grad()
def predict(model: STMaskGIT, gt_BTHW: torch.Tensor, args, generator: torch.Generator) -> torch.Tensor:
    """Predicted frames (B, T - P, H, W) for ground-truth windows gt_BTHW, prompt P = args.num_prompt_frames."""
    kwargs = dict(maskgit_steps=args.maskgit_steps, temperature=args.temperature, unmask_mode=args.unmask_mode,
                  use_cache=True, generator=generator)
    P, T = args.num_prompt_frames, gt_BTHW.shape[1]
    if args.teacher_force_time:
        # All frames 1..T-1 from their ground-truth past in one cached pass per MaskGIT step; keep P..T-1.
        samples_BTHW, _ = model.teacher_forced(gt_BTHW, **kwargs)
        return samples_BTHW[:, P - 1:]
    tokens_BTHW, _ = model.generate(gt_BTHW[:, :P], T - P, **kwargs)
    return tokens_BTHW[:, P:]


def generate(args) -> dict:
    """Run generation; returns the metadata written."""
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    model = STMaskGIT.from_pretrained(args.checkpoint_dir).to(device)
    dataset = RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride)
    check_compatible(model, dataset, args)
    s, P, T = dataset.metadata["s"], args.num_prompt_frames, args.window_size
    generator = torch.Generator(device).manual_seed(args.seed)

    outputs, seconds = [], 0.0
    indices = list(range(args.example_ind, args.example_ind + args.num_examples))
    for a in tqdm(range(0, len(indices), args.batch_size), desc="generate", unit="batch"):
        gt_BTHW = load_windows(dataset, indices[a:a + args.batch_size], s).to(device)
        t0 = time.perf_counter()
        pred_BTHW = predict(model, gt_BTHW, args, generator)
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds += time.perf_counter() - t0
        outputs.append(torch.cat([gt_BTHW[:, :P], pred_BTHW, gt_BTHW[:, P:]], dim=1).cpu())
    video_NHW = rearrange(torch.cat(outputs), "b t h w -> (b t) h w").numpy()
    frames_per_example = 2 * T - P
    logger.info("%.4f s per generated frame (%d windows, %d frames each)", seconds / (len(indices) * (T - P)),
                len(indices), T - P)

    metadata = {k: v for k, v in dataset.metadata.items() if k != "num_images"}
    metadata.update(num_prompt_frames=P, window_size=T, num_examples=len(indices), example_ind=args.example_ind,
                    frames_per_example=frames_per_example, teacher_force_time=args.teacher_force_time,
                    maskgit_steps=args.maskgit_steps, temperature=args.temperature, unmask_mode=args.unmask_mode,
                    stride=args.stride, checkpoint_dir=str(args.checkpoint_dir), val_data_dir=str(args.val_data_dir))
    # One segment per example, so that windows read back from the output never mix two examples.
    segment_ids = np.repeat(np.arange(len(indices), dtype=np.int32), frames_per_example)
    write_token_dataset(args.output_dir, video_NHW, segment_ids=segment_ids, metadata=metadata, overwrite=True)
    logger.info("wrote %d frames to %s", len(video_NHW), args.output_dir)
    return {**metadata, "num_images": len(video_NHW)}


def main(argv=None) -> None:
    args = parse_args(argv)
    logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S",
                        level=logging.INFO)
    try:
        generate(args)
    except (GenerationError, TokenDatasetError, ConfigError, CheckpointError, OSError) as e:
        sys.exit(f"generate.py: error: {e}")


if __name__ == "__main__":
    main()
