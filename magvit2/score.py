"""How close a tokenizer's reconstructions come to the real frames: the ceiling of every model that speaks its tokens.

    python -m magvit2.score --tokenizer_ckpt magvit2/pretrained/sample_world_64 \\
        --frames data/unseen/raw/val.npz data/unseen2/raw/val.npz

For each .npz of frames (key `frames`, (N, H, W, 3) uint8; `segment_ids` when it has them), every --stride-th frame
(default 15, the frames a dynamics model's windows hold) is encoded and decoded, and the reconstruction scored
against the frame: PSNR, LPIPS (AlexNet), sharpness (the mean absolute Laplacian as a share of the real frames'),
KID x 1000 between the set of reconstructions and the set of real frames (on the pooled LPIPS features, as the play
protocol), the codes used, and how many tokens stay the same from one scored frame to the next within a walk (a
dynamics model learns more easily from tokens that stay put while the view barely moves). One JSON line per file,
then one for all files together (the last line).
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, positive_int, resolve_device, run_main,
                        setup_logging)
from common.errors import InputError
from common.images import kid, psnr, sharpness
from magvit2.lpips import LPIPS
from magvit2.model import VQModel

def scored_frames(path: Path, stride: int) -> tuple:
    """(every stride-th frame (n, H, W, 3) uint8, the segment id of each (n,)) of a frames .npz."""
    if not path.is_file():
        raise InputError(f"{path}: no such file (a .npz with a 'frames' array)")
    with np.load(path, mmap_mode="r") as npz:
        if "frames" not in npz.files:
            raise InputError(f"{path}: no 'frames' array (found {npz.files})")
        frames = npz["frames"]
        if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
            raise InputError(f"{path}: frames must be uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}")
        segments = np.asarray(npz["segment_ids"]) if "segment_ids" in npz.files else np.zeros(len(frames), int)
    inds = np.arange(0, len(frames), stride)
    return np.ascontiguousarray(frames[inds]), segments[inds]


@torch.no_grad()
def score(tokenizer: VQModel, lpips: LPIPS, frames_NHW3: np.ndarray, segments_N: np.ndarray, device,
          batch_size: int = 64) -> dict:
    """The scores of one set of frames (module doc)."""
    recon, tokens, dist, feats_real, feats_recon = [], [], [], [], []
    for a in range(0, len(frames_NHW3), batch_size):
        real = torch.from_numpy(frames_NHW3[a:a + batch_size]).to(device)
        ids = tokenizer.images_to_tokens(real)
        images = tokenizer.tokens_to_images(ids)
        real_unit, images_unit = (x.permute(0, 3, 1, 2).float() / 127.5 - 1 for x in (real, images))
        dist.append(lpips(images_unit, real_unit).cpu())
        feats_real.append(lpips.pooled_features(real_unit).cpu())
        feats_recon.append(lpips.pooled_features(images_unit).cpu())
        recon.append(images.cpu())
        tokens.append(ids.cpu())
    real_all, recon_all, ids_all = torch.from_numpy(frames_NHW3), torch.cat(recon), torch.cat(tokens)
    same_walk = torch.from_numpy(segments_N[1:] == segments_N[:-1])
    unchanged = (ids_all[1:] == ids_all[:-1]).float().mean(dim=(1, 2))[same_walk]
    return {"frames": len(frames_NHW3),
            "psnr": float(psnr(recon_all, real_all, value_range=(0.0, 255.0)).mean()),
            "lpips": float(torch.cat(dist).mean()),
            "sharpness": float(sharpness(recon_all).mean() / sharpness(real_all).mean()),
            "kid_x1000": 1000 * kid(torch.cat(feats_recon), torch.cat(feats_real)),
            "codes_used": int(len(torch.unique(ids_all))),
            "tokens_unchanged": float(unchanged.mean()) if len(unchanged) else None}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m magvit2.score", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tokenizer_ckpt", required=True, help="tokenizer checkpoint directory (config.json + "
                                                          "model.safetensors) or a published magvit2.ckpt")
    p.add_argument("--frames", nargs="+", required=True, help=".npz files with a 'frames' array")
    p.add_argument("--stride", type=positive_int, default=15,
                   help="score every N-th frame (default: %(default)s, a window's frames)")
    p.add_argument("--batch_size", type=positive_int, default=64, help="frames per batch (default: %(default)s)")
    add_device_arg(p)
    add_num_threads_arg(p)
    return p.parse_args(argv)


def main(argv=None) -> int:
    setup_logging()
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    device = resolve_device(args.device)
    sets = [scored_frames(Path(p), args.stride) for p in args.frames]  # bad input fails before anything loads
    tokenizer = VQModel.from_checkpoint(args.tokenizer_ckpt, map_location=device).eval()
    lpips = LPIPS().to(device)
    for path, (frames, segments) in zip(args.frames, sets):
        print(json.dumps({"frames_file": path, **score(tokenizer, lpips, frames, segments, device, args.batch_size)}))
    if len(sets) > 1:
        # walks of different files never continue each other: offset their segment ids
        segments = np.concatenate([s + 1_000_000 * i for i, (_, s) in enumerate(sets)])
        frames = np.concatenate([f for f, _ in sets])
        print(json.dumps({"frames_file": "all", **score(tokenizer, lpips, frames, segments, device,
                                                        args.batch_size)}))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("magvit2.score", main))
