"""Memory-mapped token dataset in the 1X layout (docs/formats.md §1): reader, validation, window index, writer.

A dataset directory holds

    metadata.json        {"num_images": N, "s": s, "vocab_size": V, "hz": 30, "token_dtype": "uint32", ...}
    video.bin            token ids, token_dtype, shape (N, s, s)
    segment_ids.bin      int32 (N,), non-decreasing; a window may not cross two segments (clips)
    actions/<name>.bin   float32 (N, k) per action stream (optional)
    MANIFEST.json        size + sha256 of each file, recorded by the writer (common/integrity.py); opening a dataset
                         does not read it (video.bin can be GBs): `validate(full=True)` and `python -m data.verify`
                         check it. Datasets without one (published ones) are read as before.

Every problem with a directory is reported as a TokenDatasetError naming the offending file.
"""
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from common.errors import InputError, IntegrityError, writing
from common.integrity import update_manifest, verify_manifest

REQUIRED_KEYS = ("num_images", "s", "vocab_size", "hz")
TOKEN_DTYPES = ("uint8", "uint16", "uint32", "uint64", "int16", "int32", "int64")
DEFAULT_METADATA = {"token_dtype": "uint32", "vocab_size": 262144, "hz": 30}
# Upper bounds that no real dataset reaches; larger values mean a corrupt metadata.json.
MAX_NUM_IMAGES = 2 ** 40
MAX_S = 4096
MAX_VOCAB_SIZE = 2 ** 40
MAX_HZ = 10_000
CHUNK = 1 << 22  # elements per chunk for full scans: bounded memory on 10 M-frame datasets
SMALL_FILE_BYTES = 64 << 20  # action files up to this size are fully scanned for NaN/inf on load


class TokenDatasetError(InputError):
    """A token dataset directory (or data given to the writer) that does not follow the format."""


def _positive_int(meta: dict, key: str, limit: int, source: Path) -> int:
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, int):
        raise TokenDatasetError(f"{source}: {key!r} must be an integer, got {value!r} ({type(value).__name__})")
    if not 1 <= value <= limit:
        raise TokenDatasetError(f"{source}: {key!r} must be in [1, {limit}], got {value}")
    return value


def validate_metadata(meta, source) -> dict:
    """Check a metadata dict (types and ranges of the keys readers use); return a copy with token_dtype filled in."""
    source = Path(source)
    if not isinstance(meta, dict):
        raise TokenDatasetError(f"{source}: expected a JSON object, got {type(meta).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise TokenDatasetError(f"{source}: missing required key(s) {missing}; required: {list(REQUIRED_KEYS)}")
    meta = {"token_dtype": DEFAULT_METADATA["token_dtype"], **meta}
    _positive_int(meta, "num_images", MAX_NUM_IMAGES, source)
    s = _positive_int(meta, "s", MAX_S, source)
    _positive_int(meta, "vocab_size", MAX_VOCAB_SIZE, source)
    for key in ("h", "w"):
        if key in meta and meta[key] != s:
            raise TokenDatasetError(f"{source}: {key!r} is {meta[key]!r} but must equal s={s} (square token grid)")
    hz = meta["hz"]
    if isinstance(hz, bool) or not isinstance(hz, (int, float)) or not 0 < hz <= MAX_HZ:  # NaN fails too
        raise TokenDatasetError(f"{source}: 'hz' must be a number in (0, {MAX_HZ}], got {hz!r}")
    if meta["token_dtype"] not in TOKEN_DTYPES:
        raise TokenDatasetError(f"{source}: unknown token_dtype {meta['token_dtype']!r}; "
                                f"supported: {list(TOKEN_DTYPES)}")
    return meta


def token_dtype(meta: dict) -> np.dtype:
    """The little-endian numpy dtype of video.bin."""
    return np.dtype(meta["token_dtype"]).newbyteorder("<")


def _check_file_size(path: Path, expected: int, what: str) -> None:
    if not path.is_file():
        raise TokenDatasetError(f"{path}: file not found")
    actual = path.stat().st_size
    if actual != expected:
        raise TokenDatasetError(f"{path}: expected {expected} bytes ({what}) but found {actual} bytes; the file is "
                                f"truncated or corrupt, or metadata.json does not describe it")


def read_metadata(data_dir) -> dict:
    """Read and validate `data_dir/metadata.json`, and check that video.bin has the size it describes."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise TokenDatasetError(f"{data_dir}: token dataset directory not found")
    path = data_dir / "metadata.json"
    if not path.is_file():
        raise TokenDatasetError(f"{path}: file not found (is {data_dir} a token dataset?)")
    try:
        meta = json.loads(path.read_text())
    except ValueError as e:  # JSONDecodeError, UnicodeDecodeError
        raise TokenDatasetError(f"{path}: not valid JSON ({e})") from None
    meta = validate_metadata(meta, path)
    n, s, dtype = meta["num_images"], meta["s"], token_dtype(meta)
    _check_file_size(data_dir / "video.bin", n * s * s * dtype.itemsize,
                     f"num_images={n} x s={s} x s={s} x {dtype.itemsize} bytes of {meta['token_dtype']}")
    return meta


def _check_non_decreasing(segment_ids: np.ndarray, path: Path) -> None:
    for a in range(0, len(segment_ids) - 1, CHUNK):
        chunk = np.asarray(segment_ids[a:a + CHUNK + 1])
        bad = np.flatnonzero(chunk[1:] < chunk[:-1])
        if len(bad):
            i = a + int(bad[0])
            raise TokenDatasetError(f"{path}: segment ids must be non-decreasing, but segment_ids[{i + 1}] = "
                                    f"{segment_ids[i + 1]} < segment_ids[{i}] = {segment_ids[i]}")


def _check_finite(values: np.ndarray, path: Path, first_frame: int = 0, frame_step: int = 1) -> None:
    """values: (n, k) rows of frames first_frame, first_frame + frame_step, ..."""
    rows = max(1, CHUNK // values.shape[1])
    for a in range(0, len(values), rows):
        chunk = np.asarray(values[a:a + rows])
        if not np.isfinite(chunk).all():
            row = a + int(np.flatnonzero(~np.isfinite(chunk).all(axis=1))[0])
            raise TokenDatasetError(f"{path}: non-finite action value (NaN or inf) at frame "
                                    f"{first_frame + row * frame_step}")


def _check_token_range(tokens: np.ndarray, vocab_size: int, path: Path, first_frame: int = 0,
                       frame_step: int = 1) -> None:
    """tokens: (n, s, s) of frames first_frame, first_frame + frame_step, ...; ids must lie in [0, vocab_size)."""
    bad = (tokens >= vocab_size) | (tokens < 0)
    if bad.any():
        row, y, x = (int(i) for i in np.argwhere(bad)[0])
        raise TokenDatasetError(f"{path}: token id {tokens[row, y, x]} at frame {first_frame + row * frame_step} "
                                f"(row {y}, column {x}) is outside [0, vocab_size={vocab_size}) of metadata.json")


def _scan_action_dir(data_dir: Path, num_images: int) -> dict:
    """name -> dim for every actions/<name>.bin, sizes checked."""
    action_dir = data_dir / "actions"
    if not action_dir.is_dir():
        return {}
    dims = {}
    for path in sorted(action_dir.glob("*.bin")):
        if not path.is_file():
            raise TokenDatasetError(f"{path}: not a regular file")
        size, row = path.stat().st_size, num_images * 4
        if size == 0 or size % row:
            raise TokenDatasetError(f"{path}: {size} bytes is not num_images={num_images} x k x 4 bytes (float32) "
                                    f"for any integer k >= 1; the file is truncated or corrupt")
        dims[path.stem] = size // row
    return dims


def valid_start_mask(segment_ids, num_frames: int, window_size: int, stride: int,
                     filter_interrupts: bool) -> np.ndarray:
    """(num_frames - (window_size-1)*stride,) bool: start i is a valid window start.

    With filter_interrupts, the window's first and last frame must share a segment id (non-decreasing ids make
    that equivalent to the whole window lying in one segment).
    """
    span = (window_size - 1) * stride
    n = num_frames - span
    if n <= 0:
        return np.zeros(0, dtype=bool)
    if not filter_interrupts:
        return np.ones(n, dtype=bool)
    segment_ids = np.asarray(segment_ids)
    return segment_ids[:n] == segment_ids[span:span + n]


def filter_overlapping_starts(valid: np.ndarray, window_size: int, stride: int) -> np.ndarray:
    """Greedy non-overlapping subset of the valid starts (the published filter_overlaps), vectorized.

    Walking starts in order, a start is kept iff no kept start lies in {start - i*stride : i = 1..window_size-1}.
    Such conflicts only happen inside one residue class mod stride. Within a run of consecutive valid starts of
    one class (spaced by stride), once a start is kept the next window_size-1 are rejected and the one after is
    kept, so each run keeps first, first + P, first + 2P, ... with period P = window_size * stride. A run's first
    kept start is the run's first start unless a start kept in the previous run of the class is less than P
    before it; only such chained runs (never the case for segment-filtered windows) need a sequential pass.

    valid: (n,) bool from valid_start_mask. Returns the kept starts, int64 ascending.
    """
    n, period = len(valid), window_size * stride
    prev_valid = np.zeros(n, dtype=bool)
    prev_valid[stride:] = valid[:max(n - stride, 0)]  # prev_valid[p] = valid[p - stride]
    next_valid = np.zeros(n, dtype=bool)
    next_valid[:max(n - stride, 0)] = valid[stride:]
    run_first = np.flatnonzero(valid & ~prev_valid)
    run_last = np.flatnonzero(valid & ~next_valid)
    del prev_valid, next_valid
    # Class-major order: the i-th first and the i-th last then belong to the same run.
    run_first = run_first[np.argsort(run_first % stride, kind="stable")]
    run_last = run_last[np.argsort(run_last % stride, kind="stable")]

    first = run_first.copy()
    chained = np.zeros(len(first), dtype=bool)
    chained[1:] = (run_first[1:] % stride == run_first[:-1] % stride) & (run_first[1:] - run_last[:-1] < period)
    count = (run_last - first) // period + 1
    chain_heads = np.flatnonzero(chained[1:] & ~chained[:-1])  # a chain = head run + following chained runs
    for head in chain_heads:
        last_kept = first[head] + (count[head] - 1) * period
        i = head + 1
        while i < len(first) and chained[i]:
            first[i] = max(run_first[i], last_kept + period)
            count[i] = max(0, (run_last[i] - first[i]) // period + 1)
            if count[i]:
                last_kept = first[i] + (count[i] - 1) * period
            i += 1

    # Expand runs: kept start j of run r is first[r] + (j - offset[r]) * period, j counting over all runs.
    offset = np.cumsum(count) - count
    kept = np.repeat(first - offset * period, count) + np.arange(int(count.sum()), dtype=np.int64) * period
    kept.sort()
    return kept


def _check_window_args(window_size, stride, data_dir: Path) -> None:
    for name, value in (("window_size", window_size), ("stride", stride)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise TokenDatasetError(f"{data_dir}: {name} must be an integer >= 1, got {value!r}")


class RawTokenDataset(Dataset):
    """Windows of `window_size` frames, `stride` frames apart, from a token dataset directory (memory-mapped).

    Item idx is frames data[start : start + (window_size-1)*stride + 1 : stride] with start = valid_start_inds[idx],
    returned as a dict: "tokens" (T, s, s) int64 and "actions", a dict stream name -> (T, dim) float32 tensor of
    every stream in actions/ (empty without actions/).

    filter_interrupts: drop windows that cross two segments (needs segment_ids.bin).
    filter_overlaps: keep a subset of windows so that each frame is used at most once (validation).
    check_tokens: check each loaded window's token ids against vocab_size (cheap; errors name file and frame).
    step_mean_streams: action streams read as step means: row t of the window is the mean of the `stride` per-frame
        rows from window frame t up to (not including) frame t+1, cut at the end of the segment and of the data,
        i.e. everything commanded during the step t -> t+1 instead of the command at frame t alone.
    """

    def __init__(self, data_dir, window_size: int, stride: int = 1, filter_interrupts: bool = True,
                 filter_overlaps: bool = False, check_tokens: bool = True, step_mean_streams=()):
        self.data_dir = Path(data_dir)
        _check_window_args(window_size, stride, self.data_dir)
        self.metadata = read_metadata(self.data_dir)
        self.window_size, self.stride = int(window_size), int(stride)
        self.vocab_size = self.metadata["vocab_size"]
        self.check_tokens = check_tokens
        num_images = self.metadata["num_images"]

        seg_path = self.data_dir / "segment_ids.bin"
        self.has_segment_ids = seg_path.exists()
        if self.has_segment_ids:
            _check_file_size(seg_path, num_images * 4, f"num_images={num_images} x 4 bytes of int32")
        elif filter_interrupts:
            raise TokenDatasetError(f"{seg_path}: file not found; it is needed to drop windows that cross two "
                                    f"clips (filter_interrupts=True); pass filter_interrupts=False to use all windows")
        self.action_dims = _scan_action_dir(self.data_dir, num_images)
        self.action_names = sorted(self.action_dims)
        self.set_step_mean_streams(step_mean_streams)
        self._open_arrays()
        if self.segment_ids is not None:
            _check_non_decreasing(self.segment_ids, seg_path)
        for name in self.action_names:
            if os.path.getsize(self._action_path(name)) <= SMALL_FILE_BYTES:
                _check_finite(self.actions[name], self._action_path(name))

        needed = (self.window_size - 1) * self.stride + 1
        if needed > num_images:
            raise TokenDatasetError(f"{self.data_dir / 'video.bin'}: a window of {self.window_size} frames with "
                                    f"stride {self.stride} needs {needed} frames but the dataset has {num_images}")
        valid = valid_start_mask(self.segment_ids, num_images, self.window_size, self.stride, filter_interrupts)
        if filter_overlaps:
            self.valid_start_inds = filter_overlapping_starts(valid, self.window_size, self.stride)
        else:
            self.valid_start_inds = np.flatnonzero(valid).astype(np.int64, copy=False)
        if len(self.valid_start_inds) == 0:
            raise TokenDatasetError(f"{seg_path}: no segment is long enough for a window of {self.window_size} "
                                    f"frames with stride {self.stride} ({needed} consecutive frames of one segment)")

    def _action_path(self, name: str) -> Path:
        return self.data_dir / "actions" / f"{name}.bin"

    def set_step_mean_streams(self, names) -> None:
        """Read these action streams as step means from now on (see the class doc); () reads every row as is."""
        if isinstance(names, str):
            raise TokenDatasetError(f"{self.data_dir}: step_mean_streams must be a list of stream names, got {names!r}")
        missing = sorted(set(names) - set(self.action_names))
        if missing:
            raise TokenDatasetError(f"{self.data_dir / 'actions'}: no action stream(s) {[n + '.bin' for n in missing]}"
                                    f" to average over each step; found {self.action_names or 'none'}")
        self.step_mean_streams = frozenset(names)

    def _open_arrays(self) -> None:
        n, s = self.metadata["num_images"], self.metadata["s"]
        self.data = np.memmap(self.data_dir / "video.bin", dtype=token_dtype(self.metadata), mode="r",
                              shape=(n, s, s))
        self.segment_ids = (np.memmap(self.data_dir / "segment_ids.bin", dtype="<i4", mode="r", shape=(n,))
                            if self.has_segment_ids else None)
        self.actions = {name: np.memmap(self._action_path(name), dtype="<f4", mode="r", shape=(n, dim))
                        for name, dim in self.action_dims.items()}

    def __getstate__(self) -> dict:
        # Pickling a memmap copies the whole file into the pickle; DataLoader workers reopen them instead.
        state = self.__dict__.copy()
        for key in ("data", "segment_ids", "actions"):
            state.pop(key)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._open_arrays()

    def __len__(self) -> int:
        return len(self.valid_start_inds)

    def step_mean_rows(self, name: str, rows) -> np.ndarray:
        """(len(rows), dim) float32: for each (sorted) frame index in `rows`, the mean of stream `name` over frames
        row .. row + stride - 1, cut at the end of its segment and of the data; NaN/inf raise."""
        rows = np.asarray(rows, dtype=np.int64)
        n = len(self.actions[name])
        lo, hi = int(rows[0]), min(int(rows[-1]) + self.stride, n)
        values = np.asarray(self.actions[name][lo:hi], dtype=np.float64)
        _check_finite(values, self._action_path(name), lo)
        cumsum = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
        first = rows - lo
        end = np.minimum(first + self.stride, hi - lo)
        if self.segment_ids is not None:
            seg = np.asarray(self.segment_ids[lo:hi])
            end = np.minimum(end, np.searchsorted(seg, seg[first], side="right"))
        return ((cumsum[end] - cumsum[first]) / (end - first)[:, None]).astype(np.float32)

    def get_window_actions(self, start_ind: int) -> dict:
        """name -> (T, dim) float32 array of the window starting at frame start_ind (step means for the
        step_mean_streams); NaN/inf raise."""
        frames = slice(start_ind, start_ind + (self.window_size - 1) * self.stride + 1, self.stride)
        out = {}
        for name in self.action_names:
            if name in self.step_mean_streams:
                out[name] = self.step_mean_rows(name, np.arange(frames.start, frames.stop, frames.step))
                continue
            values = np.array(self.actions[name][frames], dtype=np.float32)
            _check_finite(values, self._action_path(name), start_ind, self.stride)
            out[name] = values
        return out

    def __getitem__(self, idx: int) -> dict:
        start_ind = int(self.valid_start_inds[idx])
        tokens_Tss = np.asarray(self.data[start_ind:start_ind + (self.window_size - 1) * self.stride + 1:self.stride])
        if self.check_tokens:
            _check_token_range(tokens_Tss, self.vocab_size, self.data_dir / "video.bin", start_ind, self.stride)
        actions = {name: torch.from_numpy(values) for name, values in self.get_window_actions(start_ind).items()}
        return {"tokens": torch.from_numpy(tokens_Tss.astype(np.int64)), "actions": actions}

    def validate(self, full: bool = True, progress=None) -> None:
        """Check token ids (< vocab_size) and action values (finite); raise on the first problem.

        full: also check every file against the digests of MANIFEST.json (when there is one; at the disk's read
        speed, progress(n_bytes) after each chunk) and scan every frame in chunks (minutes on 10 M frames);
        otherwise only the first and last window.
        """
        if not full:
            for idx in (0, len(self) - 1):
                start = int(self.valid_start_inds[idx])
                frames = self.data[start:start + (self.window_size - 1) * self.stride + 1:self.stride]
                _check_token_range(np.asarray(frames), self.vocab_size, self.data_dir / "video.bin", start, self.stride)
                self.get_window_actions(start)
            return
        rows = max(1, CHUNK // (self.metadata["s"] ** 2))
        for a in range(0, len(self.data), rows):
            _check_token_range(np.asarray(self.data[a:a + rows]), self.vocab_size, self.data_dir / "video.bin", a)
        for name in self.action_names:
            _check_finite(self.actions[name], self._action_path(name))
        try:  # after the scans, whose errors say which frame is bad; the digests catch what they cannot see
            verify_manifest(self.data_dir, progress=progress)
        except IntegrityError as e:
            raise TokenDatasetError(str(e)) from None


class TokenDatasetWriter:
    """Stream a token dataset to disk: written into a temp dir beside out_dir, renamed into place on success.

        with TokenDatasetWriter(out_dir, s=16, metadata={"hz": 10}) as writer:
            for video_nss, segment_ids_n, actions in chunks:
                writer.append(video_nss, segment_ids_n, {"driving_command": actions_n2})

    metadata is merged over the defaults (vocab_size 262144, hz 30, token_dtype uint32); num_images, s, h, w are
    derived. An exception inside the block leaves no dataset (and an existing one untouched); a full disk raises
    WriteError naming out_dir. An existing dataset is replaced (atomically swapped) only with overwrite=True.
    The digests of all files are recorded in MANIFEST.json when the dataset is completed.
    """

    def __init__(self, out_dir, s: int, metadata=None, overwrite: bool = False):
        self.out_dir = Path(out_dir)
        metadata = dict(metadata or {})
        if "num_images" in metadata:
            raise TokenDatasetError(f"{self.out_dir}: metadata must not set 'num_images'; it is derived")
        for key in ("s", "h", "w"):
            if metadata.get(key, s) != s:
                raise TokenDatasetError(f"{self.out_dir}: metadata[{key!r}]={metadata[key]!r} conflicts with the "
                                        f"frames written (s={s})")
        self.metadata = {**DEFAULT_METADATA, **metadata, "s": s, "h": s, "w": s}
        validate_metadata({**self.metadata, "num_images": 1}, self.out_dir / "metadata.json")
        self.dtype = token_dtype(self.metadata)
        self.s, self.overwrite = s, overwrite
        self.num_images = 0
        self._last_segment_id = None
        self._action_dims = None
        self._files = {}
        self._tmp_dir = None

    def _check_target(self) -> None:
        if self.out_dir.is_dir() and not any(self.out_dir.iterdir()):
            return  # an empty directory is replaced by the rename
        if self.out_dir.exists() and (not self.overwrite or not self.out_dir.is_dir()):
            raise FileExistsError(f"{self.out_dir}: already exists; pass overwrite=True to replace a dataset there")

    def __enter__(self) -> "TokenDatasetWriter":
        self._check_target()
        with writing("the token dataset", self.out_dir):
            self.out_dir.parent.mkdir(parents=True, exist_ok=True)
            self._tmp_dir = Path(tempfile.mkdtemp(prefix=f".{self.out_dir.name}.", suffix=".tmp",
                                                  dir=self.out_dir.parent))
            self._files["video"] = open(self._tmp_dir / "video.bin", "wb")
            self._files["segment_ids"] = open(self._tmp_dir / "segment_ids.bin", "wb")
        return self

    def _error(self, problem: str) -> TokenDatasetError:
        return TokenDatasetError(f"{self.out_dir}: chunk at frame {self.num_images}: {problem}")

    def _checked_video(self, video) -> np.ndarray:
        video = np.asarray(video)
        if video.ndim != 3 or video.shape[1:] != (self.s, self.s):
            raise self._error(f"video must have shape (n, {self.s}, {self.s}), got {video.shape}")
        if not (np.issubdtype(video.dtype, np.integer) or video.size == 0):
            raise self._error(f"video token ids must be integers, got dtype {video.dtype}")
        if video.size:
            limit = min(self.metadata["vocab_size"], int(np.iinfo(self.dtype).max) + 1)
            lo, hi = int(video.min()), int(video.max())
            if lo < 0 or hi >= limit:
                raise self._error(f"token ids must lie in [0, {limit}) (vocab_size {self.metadata['vocab_size']}, "
                                  f"token_dtype {self.metadata['token_dtype']}), got range [{lo}, {hi}]")
        return video.astype(self.dtype, copy=False)

    def _checked_segment_ids(self, segment_ids, n: int) -> np.ndarray:
        if segment_ids is None:
            return np.full(n, self._last_segment_id or 0, dtype="<i4")
        segment_ids = np.asarray(segment_ids)
        if segment_ids.shape != (n,) or not (np.issubdtype(segment_ids.dtype, np.integer) or n == 0):
            raise self._error(f"segment_ids must be integers of shape ({n},), got {segment_ids.dtype} "
                              f"{segment_ids.shape}")
        if n == 0:
            return segment_ids.astype("<i4")
        info = np.iinfo(np.int32)
        if segment_ids.min() < info.min or segment_ids.max() > info.max:
            raise self._error("segment_ids do not fit in int32")
        segment_ids = segment_ids.astype("<i4")
        previous = segment_ids[0] if self._last_segment_id is None else self._last_segment_id
        bad = np.flatnonzero(segment_ids < np.r_[previous, segment_ids[:-1]])
        if len(bad):
            raise self._error(f"segment_ids must be non-decreasing (also across chunks), but the chunk's "
                              f"segment_ids[{int(bad[0])}] is smaller than the id before it")
        return segment_ids

    def _checked_actions(self, actions, n: int) -> dict:
        actions = {} if actions is None else actions
        if not isinstance(actions, dict):
            raise self._error(f"actions must be a dict name -> (n, k) array, got {type(actions).__name__}")
        out = {}
        for name, values in actions.items():
            if not isinstance(name, str) or not name or Path(name).name != name or name.startswith("."):
                raise self._error(f"action name {name!r} is not a valid file name")
            values = np.asarray(values)
            if values.ndim != 2 or values.shape[0] != n or values.shape[1] < 1:
                raise self._error(f"action {name!r} must have shape ({n}, k) with k >= 1, got {values.shape}")
            if not (np.issubdtype(values.dtype, np.number) or values.size == 0):
                raise self._error(f"action {name!r} must be numeric, got dtype {values.dtype}")
            with np.errstate(over="ignore"):  # overflow to inf is reported just below
                values = values.astype("<f4")
            if not np.isfinite(values).all():
                raise self._error(f"action {name!r} has NaN or inf values (also after conversion to float32)")
            out[name] = values
        dims = {name: v.shape[1] for name, v in out.items()}
        if self._action_dims is not None and dims != self._action_dims:
            raise self._error(f"actions {dims} differ from those of the first chunk {self._action_dims}")
        return out

    def append(self, video_chunk, segment_ids_chunk=None, actions_chunk=None) -> None:
        """Append n frames. video_chunk (n, s, s) int; segment_ids_chunk (n,) int, non-decreasing across chunks
        (None: continue the last segment); actions_chunk dict name -> (n, k) float, same names and k every chunk."""
        if self._tmp_dir is None:
            raise RuntimeError("TokenDatasetWriter.append must be called inside its `with` block")
        video = self._checked_video(video_chunk)
        n = len(video)
        segment_ids = self._checked_segment_ids(segment_ids_chunk, n)
        actions = self._checked_actions(actions_chunk, n)
        with writing("the token dataset", self.out_dir):
            if self._action_dims is None:
                self._action_dims = {name: v.shape[1] for name, v in actions.items()}
                if actions:
                    (self._tmp_dir / "actions").mkdir()
                for name in actions:
                    self._files[f"actions/{name}"] = open(self._tmp_dir / "actions" / f"{name}.bin", "wb")
            _write_array(self._files["video"], video)
            _write_array(self._files["segment_ids"], segment_ids)
            for name, values in actions.items():
                _write_array(self._files[f"actions/{name}"], values)
        self.num_images += n
        if n:
            self._last_segment_id = int(segment_ids[-1])

    def _close_files(self) -> None:
        for f in self._files.values():
            f.close()
        self._files = {}

    def _finish(self) -> None:
        if self.num_images == 0:
            raise TokenDatasetError(f"{self.out_dir}: no frames were written; a dataset needs at least one")
        self.metadata["num_images"] = self.num_images
        (self._tmp_dir / "metadata.json").write_text(json.dumps(self.metadata, indent=2) + "\n")
        update_manifest(self._tmp_dir)
        self._check_target()
        if not self.out_dir.exists() or not any(self.out_dir.iterdir()):
            os.replace(self._tmp_dir, self.out_dir)
            return
        # Swap: move the old dataset aside, move the new one in, then delete the old one.
        old_dir = Path(tempfile.mkdtemp(prefix=f".{self.out_dir.name}.", suffix=".old", dir=self.out_dir.parent))
        os.replace(self.out_dir, old_dir / "dataset")
        try:
            os.replace(self._tmp_dir, self.out_dir)
        except OSError:
            os.replace(old_dir / "dataset", self.out_dir)
            raise
        finally:
            shutil.rmtree(old_dir, ignore_errors=True)

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            with writing("the token dataset", self.out_dir):
                self._close_files()  # flushes the last buffered chunk: a full disk can show up here
                if exc_type is None:
                    self._finish()
        finally:
            if self._tmp_dir.exists():
                shutil.rmtree(self._tmp_dir, ignore_errors=True)
            self._tmp_dir = None
        return False


def _write_array(f, array: np.ndarray) -> None:
    """Append the array's bytes to an open file. Not ndarray.tofile: on a full disk it raises a bare "n requested
    and m written" OSError without errno, which cannot be told apart from other errors."""
    f.write(np.ascontiguousarray(array).data)


def write_token_dataset(out_dir, video, segment_ids=None, actions=None, metadata=None,
                        overwrite: bool = False) -> Path:
    """Write a whole token dataset at once (see TokenDatasetWriter). video (N, s, s) int; segment_ids (N,) int
    (default all zeros); actions dict name -> (N, k) float. Returns out_dir as a Path."""
    video = np.asarray(video)
    if video.ndim != 3 or video.shape[1] != video.shape[2]:
        raise TokenDatasetError(f"{out_dir}: video must have shape (N, s, s), got {video.shape}")
    if segment_ids is None:
        segment_ids = np.zeros(len(video), dtype=np.int32)
    with TokenDatasetWriter(out_dir, video.shape[1], metadata=metadata, overwrite=overwrite) as writer:
        writer.append(video, segment_ids, actions)
    return Path(out_dir)
