"""Corrupted token datasets either load correctly or raise TokenDatasetError naming the offending file."""
import json
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from data import RawTokenDataset, TokenDatasetError, write_token_dataset
from data import token_dataset

N, S, VOCAB, SEGMENT_LEN = 48, 2, 32, 16
HOSTILE = settings(max_examples=50, deadline=None)

window_params = st.tuples(st.integers(1, 5), st.integers(1, 3), st.booleans())  # longest window: 13 frames
json_values = st.one_of(
    st.none(), st.booleans(), st.integers(-2 ** 70, 2 ** 70), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6), st.lists(st.integers(-3, 3), max_size=2), st.dictionaries(st.text(max_size=2), st.integers()),
    st.sampled_from([0, 1, 2, 3, 16, 31, 32, 33, 48, 2 ** 16, "uint16", "int32", "uint64", "float32", "uint32"]),
)


def build(path: Path) -> dict:
    """A valid dataset; returns the arrays it holds."""
    rng = np.random.default_rng(0)
    arrays = {"video": rng.integers(0, VOCAB, (N, S, S)), "segment_ids": np.arange(N) // SEGMENT_LEN,
              "cmd": rng.normal(size=(N, 2)), "grip": rng.random((N, 1))}
    write_token_dataset(path, arrays["video"], arrays["segment_ids"],
                        {"cmd": arrays["cmd"], "grip": arrays["grip"]}, metadata={"vocab_size": VOCAB})
    return arrays


def load_or_explain(path: Path, params, culprit: str, arrays: dict, must_fail: bool = False) -> None:
    """Load every window and validate; on success the items must match `arrays`, on failure name `culprit`."""
    window_size, stride, filter_overlaps = params
    try:
        ds = RawTokenDataset(path, window_size, stride, filter_overlaps=filter_overlaps)
        items = [ds[i] for i in range(len(ds))]
        ds.validate(full=True)
    except TokenDatasetError as e:
        assert culprit in str(e), f"error does not name {culprit}: {e}"
        return
    assert not must_fail, f"corrupting {culprit} went unnoticed"
    segment_ids = np.fromfile(path / "segment_ids.bin", dtype="<i4")
    for start, item in zip(ds.valid_start_inds, items):
        frames = slice(start, start + (window_size - 1) * stride + 1, stride)
        np.testing.assert_array_equal(item["tokens"].numpy(), arrays["video"][frames])
        np.testing.assert_allclose(item["actions"]["cmd"].numpy(), arrays["cmd"][frames].astype(np.float32))
        assert segment_ids[frames][0] == segment_ids[frames][-1]


@HOSTILE
@given(key=st.sampled_from(["num_images", "s", "vocab_size", "hz", "token_dtype", "h", "w", "other"]),
       value=st.one_of(st.just("<delete>"), json_values), params=window_params)
def test_corrupt_metadata_value(key, value, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        meta = json.loads((path / "metadata.json").read_text())
        if value == "<delete>":
            meta.pop(key, None)
        else:
            meta[key] = value
        (path / "metadata.json").write_text(json.dumps(meta))
        load_or_explain(path, params, "metadata.json", arrays)


@HOSTILE
@given(content=st.one_of(st.binary(max_size=60), st.text(max_size=60), json_values.map(json.dumps)),
       params=window_params)
def test_garbage_metadata_file(content, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        write = (path / "metadata.json").write_bytes if isinstance(content, bytes) else \
            (path / "metadata.json").write_text
        write(content)
        load_or_explain(path, params, "metadata.json", arrays)


@HOSTILE
@given(name=st.sampled_from(["video.bin", "segment_ids.bin", "actions/cmd.bin", "actions/grip.bin"]),
       delta=st.integers(-150, 150).filter(bool), params=window_params)
def test_truncated_or_padded_bin(name, delta, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        with open(path / name, "r+b") as f:
            f.truncate(max(0, (path / name).stat().st_size + delta))
        load_or_explain(path, params, Path(name).name, arrays, must_fail=True)


@HOSTILE
@given(frame=st.integers(0, N - 1), row=st.integers(0, S - 1), col=st.integers(0, S - 1),
       value=st.one_of(st.integers(0, VOCAB + 2), st.integers(0, 2 ** 32 - 1)), params=window_params)
def test_token_ids(frame, row, col, value, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        arrays["video"][frame, row, col] = value
        arrays["video"].astype("<u4").tofile(path / "video.bin")
        load_or_explain(path, params, "video.bin", arrays, must_fail=value >= VOCAB)


@HOSTILE
@given(name=st.sampled_from(["cmd", "grip"]), frame=st.integers(0, N - 1), col=st.integers(0, 1),
       value=st.sampled_from([np.nan, np.inf, -np.inf]), big_file=st.booleans(), params=window_params)
def test_non_finite_actions(name, frame, col, value, big_file, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        arrays[name][frame, col % arrays[name].shape[1]] = value
        arrays[name].astype("<f4").tofile(path / "actions" / f"{name}.bin")
        # big_file: pretend the file is too big for the scan on load, so the per-window check must catch it.
        with mock.patch.object(token_dataset, "SMALL_FILE_BYTES", 0 if big_file else token_dataset.SMALL_FILE_BYTES):
            load_or_explain(path, params, f"{name}.bin", arrays, must_fail=True)


@HOSTILE
@given(edits=st.lists(st.tuples(st.integers(0, N - 1), st.integers(-2 ** 31, 2 ** 31 - 1)), min_size=1, max_size=3),
       params=window_params)
def test_corrupt_segment_ids(edits, params):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds"
        arrays = build(path)
        segment_ids = arrays["segment_ids"].astype("<i4")
        for index, value in edits:
            segment_ids[index] = value
        segment_ids.tofile(path / "segment_ids.bin")
        load_or_explain(path, params, "segment_ids.bin", arrays)
