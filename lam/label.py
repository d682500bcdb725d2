"""Label a token dataset with a trained LAM's latent actions: writes TOKEN_DIR/actions/latent_action.bin.

    python -m lam.label --lam_dir data/lam --frames data/sample/raw/train.npz \
        --token_dir data/sample/train_tokens

The token dataset must be built from the same frames, in the same order (same N, same segment boundaries).

Output: `actions/latent_action.bin`, float32 (N, 1). Row f holds the code (0 .. codebook_size - 1) of the
transition from frame f - stride to frame f, i.e. the action that leads into frame f (with num_past_frames P > 1
the LAM also sees frames f - P*stride .. f - 2*stride). Fallback for frames without a full transition inside their
segment (the first P*stride frames of each segment): the code of the first valid transition later in the same
segment; in a segment too short to have any, the most frequent code of the file. The dynamics model samples its
windows within one segment, so only a window's first frame can carry a fallback, and it is always a prompt frame.

Sidecar `actions/latent_action.json` records latent_action_stride, latent_action_codebook_size,
latent_action_num_past_frames, the fallback counts and the code histogram; metadata.json is left untouched.
"""
import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch

from common.cli import (add_device_arg, add_num_threads_arg, apply_cpu_settings, positive_int, resolve_device,
                        run_main, setup_logging)
from common.config import load_json
from common.errors import DataMismatchError
from common.files import atomic_file
from common.integrity import read_manifest, update_manifest
from lam.data import infer_codes, load_frames_npz, valid_targets
from lam.model import LAM

logger = logging.getLogger("label_latent_actions")
ACTION_NAME = "latent_action"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--lam_dir", default="data/lam", help="trained LAM directory (config.json + model.safetensors)")
    p.add_argument("--frames", required=True,
                   help="raw frames .npz (frames (N,H,W,3) uint8, segment_ids (N,)) the token dataset was built from")
    p.add_argument("--token_dir", required=True,
                   help="token dataset directory (metadata.json, segment_ids.bin) to add actions/latent_action.bin to")
    p.add_argument("--batch_size", type=positive_int, default=256, help="transitions per LAM batch")
    add_device_arg(p)
    add_num_threads_arg(p)
    return p.parse_args(argv)


def check_token_dir(token_dir: Path, segment_ids: np.ndarray, frames_path) -> None:
    """The token dataset must hold the same frames: same count and same segment boundaries."""
    meta = load_json(token_dir / "metadata.json", "token dataset metadata")
    n = len(segment_ids)
    if meta.get("num_images") != n:
        raise DataMismatchError(f"{token_dir / 'metadata.json'}: num_images {meta.get('num_images')} but {frames_path} "
                                f"has {n} frames; the token dataset must be built from the same frames in the same "
                                f"order")
    seg_path = token_dir / "segment_ids.bin"
    if not seg_path.is_file():
        return
    if seg_path.stat().st_size != 4 * n:
        raise DataMismatchError(f"{seg_path}: {seg_path.stat().st_size} bytes, expected {4 * n} (int32 x {n} "
                                f"frames)")
    token_segments = np.fromfile(seg_path, dtype=np.int32)
    if not np.array_equal(np.diff(token_segments) != 0, np.diff(segment_ids) != 0):
        raise DataMismatchError(f"{seg_path}: segment boundaries differ from those of {frames_path}; the token "
                                f"dataset must be built from the same frames in the same order")


def fill_codes(segment_ids: np.ndarray, targets: np.ndarray, codes: np.ndarray,
               codebook_size: int) -> tuple[np.ndarray, dict]:
    """Per-frame codes (N,) from the codes of the valid transitions ending at `targets` (sorted), with the
    documented fallback for the other frames; also returns fallback counts."""
    n = len(segment_ids)
    out = np.full(n, -1, dtype=np.int64)
    out[targets] = codes
    changes = np.concatenate([[0], np.cumsum(segment_ids[1:] != segment_ids[:-1])])
    missing = np.flatnonzero(out < 0)
    later = np.searchsorted(targets, missing)  # first valid target after each missing frame
    has_later = later < len(targets)
    same_segment = np.zeros_like(has_later)
    same_segment[has_later] = changes[targets[later[has_later]]] == changes[missing[has_later]]
    out[missing[same_segment]] = codes[later[same_segment]]
    most_frequent = int(np.bincount(codes, minlength=codebook_size).argmax()) if len(codes) else 0
    out[missing[~same_segment]] = most_frequent
    return out, {"num_inferred": int(len(targets)), "num_fallback_later_in_segment": int(same_segment.sum()),
                 "num_fallback_most_frequent": int((~same_segment).sum())}


def label(args) -> dict:
    apply_cpu_settings(args.num_threads)
    device = resolve_device(args.device)
    model = LAM.from_pretrained(args.lam_dir, device=device).eval()
    cfg = model.config
    data = load_frames_npz(args.frames)
    frame_shape = (cfg.image_size, cfg.image_size, cfg.image_channels)
    if data["frames"].shape[1:] != frame_shape:
        raise DataMismatchError(f"{args.frames}: frames are {data['frames'].shape[1:]}, the LAM in {args.lam_dir} "
                                f"expects {frame_shape}")
    token_dir = Path(args.token_dir)
    check_token_dir(token_dir, data["segment_ids"], args.frames)

    targets = valid_targets(data["segment_ids"], cfg.stride * cfg.num_past_frames)
    codes = infer_codes(model, torch.from_numpy(data["frames"]), targets, args.batch_size, device)
    per_frame, counts = fill_codes(data["segment_ids"], targets, codes, cfg.codebook_size)

    actions_dir = token_dir / "actions"
    actions_dir.mkdir(exist_ok=True)
    array_N1 = per_frame.astype(np.float32).reshape(-1, 1)
    atomic_file(actions_dir / f"{ACTION_NAME}.bin", lambda tmp: tmp.write_bytes(array_N1.tobytes()), "the latent action labels")
    sidecar = {
        "latent_action_stride": cfg.stride,
        "latent_action_codebook_size": cfg.codebook_size,
        "latent_action_num_past_frames": cfg.num_past_frames,
        "num_images": len(per_frame),
        **counts,
        "fallback": "frames without a full transition in their segment get the code of the first valid transition "
                    "later in that segment, else the most frequent code",
        "code_histogram": np.bincount(per_frame, minlength=cfg.codebook_size).tolist(),
        "lam_dir": str(args.lam_dir),
        "frames": str(args.frames),
    }
    text = json.dumps(sidecar, indent=2) + "\n"
    atomic_file(actions_dir / f"{ACTION_NAME}.json", lambda tmp: tmp.write_text(text), "the latent action sidecar")
    if read_manifest(token_dir) is not None:  # keep a dataset with recorded digests fully verifiable
        update_manifest(token_dir, [f"actions/{ACTION_NAME}.bin", f"actions/{ACTION_NAME}.json"])
    return sidecar


def main(argv=None):
    setup_logging()
    args = parse_args(argv)
    sidecar = label(args)
    logger.info("wrote %s/actions/%s.bin: %s", args.token_dir, ACTION_NAME,
                {k: v for k, v in sidecar.items() if k.startswith("num")})


if __name__ == "__main__":
    sys.exit(run_main("lam.label", main))
