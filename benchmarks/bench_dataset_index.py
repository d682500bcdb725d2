"""Window index of a train_v1.1-sized token dataset: vectorized RawTokenDataset vs the published per-frame loops.

Builds a dataset of --num_frames frames in a temp dir (video.bin sparse, so it takes no disk; real segment ids with
segment lengths of a few thousand frames), then times
  - index: RawTokenDataset(...) with filter_interrupts (metadata and size checks, segment id scan, window starts),
  - non-overlap filter: RawTokenDataset(..., filter_overlaps=True) minus the index time,
against the published algorithm (Python loops over frames on the memmap). The reference is slow, so it runs on the
first --reference_frames frames and its time is extrapolated linearly to --num_frames; its result is checked
against ours on that prefix.
"""
import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common.cli import existing_dir, non_negative_int, positive_int, run_main
from data import RawTokenDataset
from data.token_dataset import filter_overlapping_starts, valid_start_mask


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def make_sparse_dataset(path: Path, num_frames: int, s: int, min_len: int, max_len: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    with open(path / "segment_ids.bin", "wb") as f:  # segment by segment, so the peak RSS stays that of indexing
        written, segment = 0, 0
        while written < num_frames:
            length = min(int(rng.integers(min_len, max_len + 1)), num_frames - written)
            np.full(length, segment, dtype="<i4").tofile(f)
            written, segment = written + length, segment + 1
    with open(path / "video.bin", "wb") as f:
        f.truncate(num_frames * s * s * 4)
    metadata = {"token_dtype": "uint32", "s": s, "h": s, "w": s, "vocab_size": 262144, "hz": 30,
                "num_images": num_frames}
    (path / "metadata.json").write_text(json.dumps(metadata))


def reference_index(segment_ids, num_frames: int, window_size: int, stride: int):
    """The published loops: per-frame start filter, then the per-start overlap filter.

    Returns (starts, kept, seconds of the start filter, seconds of the overlap filter).
    """
    t0 = time.perf_counter()
    video_len = (window_size - 1) * stride
    starts = []
    for start in range(num_frames - video_len):
        if segment_ids[start] == segment_ids[start + video_len]:
            starts.append(start)
    t1 = time.perf_counter()
    kept = []
    for start in starts:
        overlapping = {start - i * stride for i in range(1, window_size)}
        for existing in kept[-window_size * stride:]:
            if existing in overlapping:
                break
        else:
            kept.append(start)
    return starts, kept, t1 - t0, time.perf_counter() - t1


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num_frames", type=positive_int, default=10_800_000,
                        help="frames in the dataset (train_v1.1: 10.8 M)")
    parser.add_argument("--reference_frames", type=positive_int, default=500_000,
                        help="frames the slow reference runs on; its time is extrapolated linearly")
    parser.add_argument("--window_size", type=positive_int, default=16, help="frames per window (challenge: 16)")
    parser.add_argument("--stride", type=positive_int, default=15,
                        help="frames between window frames (challenge: 15)")
    parser.add_argument("--s", type=positive_int, default=16,
                        help="token grid side (the sparse video.bin is N*s*s*4 bytes)")
    parser.add_argument("--min_segment_len", type=positive_int, default=1000,
                        help="shortest segment (clip), in frames")
    parser.add_argument("--max_segment_len", type=positive_int, default=6000,
                        help="longest segment (clip), in frames")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed runs of ours; the best is reported")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed for the segment lengths")
    parser.add_argument("--tmp_dir", type=existing_dir, default=None,
                        help="where to create the temp dataset (default: system temp)")
    args = parser.parse_args(argv)
    if args.min_segment_len > args.max_segment_len:
        parser.error(f"--min_segment_len {args.min_segment_len} is above --max_segment_len {args.max_segment_len}")

    with tempfile.TemporaryDirectory(dir=args.tmp_dir) as tmp:
        path = Path(tmp)
        make_sparse_dataset(path, args.num_frames, args.s, args.min_segment_len, args.max_segment_len, args.seed)
        rss_before = peak_rss_mb()
        w, st = args.window_size, args.stride

        t_index = best_time(lambda: RawTokenDataset(path, w, st), args.repeats)
        t_both = best_time(lambda: RawTokenDataset(path, w, st, filter_overlaps=True), args.repeats)
        ds = RawTokenDataset(path, w, st)
        valid = valid_start_mask(ds.segment_ids, args.num_frames, w, st, True)
        t_filter = best_time(lambda: filter_overlapping_starts(valid, w, st), args.repeats)
        kept = RawTokenDataset(path, w, st, filter_overlaps=True).valid_start_inds
        rss_ours = peak_rss_mb()

        n_ref = min(args.reference_frames, args.num_frames)
        ref_starts, ref_kept, t_ref_index, t_ref_filter = reference_index(ds.segment_ids, n_ref, w, st)
        prefix = valid_start_mask(ds.segment_ids[:n_ref], n_ref, w, st, True)
        assert np.array_equal(np.flatnonzero(prefix), ref_starts), "index differs from the reference"
        assert np.array_equal(filter_overlapping_starts(prefix, w, st), ref_kept), "filter differs from the reference"
        scale = args.num_frames / n_ref
        t_ref_index, t_ref_filter = t_ref_index * scale, t_ref_filter * scale

    print(f"dataset: {args.num_frames:,} frames, window {w}, stride {st}, segments of "
          f"{args.min_segment_len}-{args.max_segment_len} frames; {len(ds):,} windows, {len(kept):,} non-overlapping")
    print(f"reference: published per-frame loops run on the first {n_ref:,} frames (same result there), "
          f"times extrapolated x{scale:.1f}")
    print(f"index (full RawTokenDataset init):  ours {t_index:8.3f} s   reference {t_ref_index:8.2f} s   "
          f"speed-up {t_ref_index / t_index:8.0f}x")
    print(f"non-overlap filter (init delta):    ours {t_both - t_index:8.3f} s   reference {t_ref_filter:8.2f} s   "
          f"speed-up {t_ref_filter / max(t_both - t_index, 1e-9):8.0f}x")
    print(f"non-overlap filter (function only): ours {t_filter:8.3f} s")
    print(f"peak RSS: {rss_before:.0f} MB before indexing, {rss_ours:.0f} MB after ours "
          f"(+{rss_ours - rss_before:.0f} MB)")


if __name__ == "__main__":
    sys.exit(run_main("bench_dataset_index.py", main))
