"""RawTokenDataset: window index vs the published per-frame algorithm, item content, validation, writer."""
import json
import pickle

import numpy as np
import pytest
import torch

from data import RawTokenDataset, TokenDatasetError, TokenDatasetWriter, read_metadata, write_token_dataset
from data import token_dataset
from data.token_dataset import filter_overlapping_starts, valid_start_mask


def reference_starts(segment_ids, num_frames, window_size, stride, filter_interrupts, filter_overlaps):
    """The published algorithm, frame by frame."""
    video_len = (window_size - 1) * stride
    starts = [i for i in range(num_frames - video_len)
              if not (filter_interrupts and segment_ids[i] != segment_ids[i + video_len])]
    if not filter_overlaps:
        return starts
    kept = []
    for start in starts:
        overlapping = {start - i * stride for i in range(1, window_size)}
        if not any(k in overlapping for k in kept[-window_size * stride:]):
            kept.append(start)
    return kept


def random_segment_ids(rng, n):
    new_segment = rng.random(n) < rng.choice([0.0, 0.02, 0.1, 0.4])
    return (np.cumsum(new_segment) + rng.integers(0, 5)).astype(np.int32)


def make_dataset(path, n=40, s=2, vocab_size=16, segment_ids=None, actions=None, seed=0, **metadata):
    rng = np.random.default_rng(seed)
    video = rng.integers(0, vocab_size, size=(n, s, s))
    write_token_dataset(path, video, segment_ids, actions, metadata={"vocab_size": vocab_size, **metadata})
    return video


WINDOW_STRIDES = [(1, 1), (2, 1), (3, 2), (5, 3), (4, 7), (16, 1), (16, 15)]


@pytest.mark.parametrize("window_size,stride", WINDOW_STRIDES)
def test_index_matches_published_algorithm(window_size, stride):
    rng = np.random.default_rng(window_size * 100 + stride)
    for _ in range(60):
        n = int(rng.integers(1, 600))
        seg = random_segment_ids(rng, n)
        for filter_interrupts in (False, True):
            valid = valid_start_mask(seg, n, window_size, stride, filter_interrupts)
            expected = reference_starts(seg, n, window_size, stride, filter_interrupts, False)
            np.testing.assert_array_equal(np.flatnonzero(valid), expected)
            expected = reference_starts(seg, n, window_size, stride, filter_interrupts, True)
            np.testing.assert_array_equal(filter_overlapping_starts(valid, window_size, stride), expected)


@pytest.mark.parametrize("window_size,stride", [(2, 1), (3, 2), (4, 3), (16, 15)])
def test_overlap_filter_on_arbitrary_valid_sets(window_size, stride):
    """Gaps shorter than a window between runs of a residue class (the sequential branch) are handled exactly."""
    rng = np.random.default_rng(stride)
    for _ in range(100):
        valid = rng.random(int(rng.integers(1, 400))) < rng.random()
        kept = []
        for start in np.flatnonzero(valid):
            if not any((start - k) % stride == 0 and 0 < start - k < window_size * stride for k in kept):
                kept.append(start)
        np.testing.assert_array_equal(filter_overlapping_starts(valid, window_size, stride), kept)


@pytest.mark.parametrize("window_size,stride", WINDOW_STRIDES)
def test_dataset_index_and_items(tmp_path, window_size, stride):
    rng = np.random.default_rng(7)
    for trial in range(4):
        n = (window_size - 1) * stride + int(rng.integers(1, 200))
        seg = np.sort(rng.integers(0, 3, n)).astype(np.int32)
        video = make_dataset(tmp_path / str(trial), n=n, segment_ids=seg, seed=trial)
        for filter_interrupts in (False, True):
            for filter_overlaps in (False, True):
                expected = reference_starts(seg, n, window_size, stride, filter_interrupts, filter_overlaps)
                if not expected:
                    with pytest.raises(TokenDatasetError, match="segment_ids.bin"):
                        RawTokenDataset(tmp_path / str(trial), window_size, stride, filter_interrupts, filter_overlaps)
                    continue
                ds = RawTokenDataset(tmp_path / str(trial), window_size, stride, filter_interrupts, filter_overlaps)
                assert ds.valid_start_inds.dtype == np.int64
                np.testing.assert_array_equal(ds.valid_start_inds, expected)
                item = ds[len(ds) - 1]
                start = expected[-1]
                frames = video[start:start + (window_size - 1) * stride + 1:stride]
                assert frames.shape[0] == window_size
                assert ds.valid_start_inds[len(ds) - 1] == start
                assert torch.equal(item["tokens"], torch.from_numpy(frames))


def test_item_content_and_actions(tmp_path):
    n, rng = 50, np.random.default_rng(0)
    actions = {"b_cmd": rng.normal(size=(n, 2)), "a_joint": rng.normal(size=(n, 3)), "c_grip": rng.random((n, 1))}
    video = make_dataset(tmp_path, n=n, s=3, vocab_size=100, actions=actions)
    ds = RawTokenDataset(tmp_path, window_size=4, stride=3)
    assert ds.action_names == ["a_joint", "b_cmd", "c_grip"]
    assert ds.action_dims == {"a_joint": 3, "b_cmd": 2, "c_grip": 1}
    assert ds.data.shape == (n, 3, 3) and ds.vocab_size == 100 and ds.metadata["hz"] == 30
    item = ds[5]
    start = int(ds.valid_start_inds[5])
    assert start == 5
    expected = torch.from_numpy(video[start:start + 10:3])
    assert set(item) == {"tokens", "actions"}
    assert item["tokens"].dtype == torch.int64 and item["tokens"].shape == (4, 3, 3)
    assert torch.equal(item["tokens"], expected)
    assert list(item["actions"]) == ds.action_names
    for k in ds.action_names:
        assert item["actions"][k].dtype == torch.float32 and item["actions"][k].shape == (4, ds.action_dims[k])
        np.testing.assert_allclose(item["actions"][k].numpy(), actions[k][start:start + 10:3].astype(np.float32))
    window = ds.get_window_actions(start)
    np.testing.assert_allclose(window["b_cmd"], actions["b_cmd"][start:start + 10:3].astype(np.float32))


def brute_step_mean(values, segment_ids, frame, stride):
    """Mean of rows frame .. frame + stride - 1 that lie in frame's segment and in the data."""
    rows = [f for f in range(frame, min(frame + stride, len(values)))
            if segment_ids is None or segment_ids[f] == segment_ids[frame]]
    return values[rows].astype(np.float64).mean(axis=0)


@pytest.mark.parametrize("window_size,stride", [(3, 4), (2, 1), (4, 3), (1, 5)])
def test_step_mean_streams(tmp_path, window_size, stride):
    n, rng = 70, np.random.default_rng(stride)
    segment_ids = np.repeat(np.arange(4), [9, 25, 4, 32]).astype(np.int32)
    actions = {"cmd": rng.normal(size=(n, 2)) * 50 + 80, "grip": rng.random((n, 1))}
    make_dataset(tmp_path, n=n, segment_ids=segment_ids, actions=actions)
    plain = RawTokenDataset(tmp_path, window_size, stride)
    ds = RawTokenDataset(tmp_path, window_size, stride, step_mean_streams=["cmd"])
    assert ds.step_mean_streams == {"cmd"}
    for idx in range(len(ds)):
        start = int(ds.valid_start_inds[idx])
        item = ds[idx]["actions"]
        frames = range(start, start + (window_size - 1) * stride + 1, stride)
        expected = np.stack([brute_step_mean(actions["cmd"], segment_ids, f, stride) for f in frames])
        np.testing.assert_allclose(item["cmd"].numpy(), expected, rtol=1e-6)
        assert item["cmd"].dtype == torch.float32
        assert torch.equal(item["grip"], plain[idx]["actions"]["grip"])  # other streams: the frame's row
    # every row at once (the statistics' path), incl. rows whose step is cut by a segment end or the data's end
    rows = ds.step_mean_rows("cmd", np.arange(n))
    np.testing.assert_allclose(rows, [brute_step_mean(actions["cmd"], segment_ids, f, stride) for f in range(n)],
                               rtol=1e-6)
    if stride == 1:
        np.testing.assert_allclose(rows, actions["cmd"].astype(np.float32))
    (tmp_path / "segment_ids.bin").unlink()
    loose = RawTokenDataset(tmp_path, window_size, stride, filter_interrupts=False, step_mean_streams=["cmd"])
    np.testing.assert_allclose(loose.step_mean_rows("cmd", np.arange(n)),
                               [brute_step_mean(actions["cmd"], None, f, stride) for f in range(n)], rtol=1e-6)


def test_step_mean_streams_bad(tmp_path, monkeypatch):
    actions = np.zeros((20, 2))
    make_dataset(tmp_path, n=20, actions={"cmd": actions})
    with pytest.raises(TokenDatasetError, match="joint.bin.*found.*cmd"):
        RawTokenDataset(tmp_path, 2, step_mean_streams=["joint"])
    with pytest.raises(TokenDatasetError, match="list of stream names"):
        RawTokenDataset(tmp_path, 2, step_mean_streams="cmd")
    actions[13, 1] = np.nan
    actions.astype(np.float32).tofile(tmp_path / "actions" / "cmd.bin")
    monkeypatch.setattr(token_dataset, "SMALL_FILE_BYTES", 0)  # big files: checked as windows are read
    ds = RawTokenDataset(tmp_path, 2, stride=3, step_mean_streams=["cmd"])
    ds[7]  # frames 7 and 10: steps over frames 7..12
    plain = RawTokenDataset(tmp_path, 2, stride=3)
    plain[9]  # frames 9 and 12 themselves are finite ...
    with pytest.raises(TokenDatasetError, match="cmd.bin.*non-finite.*frame 13"):
        ds[9]  # ... but the step from frame 12 reaches frame 13


def test_no_actions_and_no_segment_ids(tmp_path):
    make_dataset(tmp_path, n=20)
    (tmp_path / "segment_ids.bin").unlink()
    with pytest.raises(TokenDatasetError, match="segment_ids.bin.*filter_interrupts"):
        RawTokenDataset(tmp_path, window_size=3)
    ds = RawTokenDataset(tmp_path, window_size=3, filter_interrupts=False)
    assert ds.segment_ids is None and ds.action_names == [] and ds.actions == {}
    assert len(ds) == 18 and ds[0]["actions"] == {}


def test_pickle_reopens_memmaps(tmp_path):
    make_dataset(tmp_path, n=1000, s=8, actions={"a": np.ones((1000, 2))})
    ds = RawTokenDataset(tmp_path, window_size=4, stride=2)
    blob = pickle.dumps(ds)
    assert len(blob) < 1000 * 8 * 8 * 4 // 10  # the video itself is not in the pickle
    copy = pickle.loads(blob)
    assert torch.equal(copy[3]["tokens"], ds[3]["tokens"])
    assert copy[3]["actions"].keys() == ds[3]["actions"].keys() == {"a"}
    assert torch.equal(copy[3]["actions"]["a"], ds[3]["actions"]["a"])


def test_dataloader_with_workers(tmp_path):
    make_dataset(tmp_path, n=30)
    ds = RawTokenDataset(tmp_path, window_size=4)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2)
    batch = next(iter(loader))
    assert batch["tokens"].shape == (4, 4, 2, 2)
    assert torch.equal(batch["tokens"][1], ds[1]["tokens"])


def test_read_metadata(tmp_path):
    make_dataset(tmp_path, n=10, hz=10, tokenizer_ckpt="x.ckpt")
    meta = read_metadata(tmp_path)
    assert meta["num_images"] == 10 and meta["s"] == meta["h"] == meta["w"] == 2
    assert meta["hz"] == 10 and meta["token_dtype"] == "uint32" and meta["tokenizer_ckpt"] == "x.ckpt"


# ---------------------------------------------------------------- validation

def edit_metadata(path, **changes):
    meta = json.loads((path / "metadata.json").read_text())
    for key, value in changes.items():
        if value is None:
            del meta[key]
        else:
            meta[key] = value
    (path / "metadata.json").write_text(json.dumps(meta))


def test_missing_files(tmp_path):
    with pytest.raises(TokenDatasetError, match="nope.*not found"):
        RawTokenDataset(tmp_path / "nope", 2)
    tmp_path.joinpath("empty").mkdir()
    with pytest.raises(TokenDatasetError, match="metadata.json.*not found"):
        RawTokenDataset(tmp_path / "empty", 2)
    make_dataset(tmp_path / "d")
    (tmp_path / "d" / "video.bin").unlink()
    with pytest.raises(TokenDatasetError, match="video.bin.*not found"):
        read_metadata(tmp_path / "d")


def test_invalid_json(tmp_path):
    make_dataset(tmp_path)
    (tmp_path / "metadata.json").write_text('{"num_images": 40,')
    with pytest.raises(TokenDatasetError, match="metadata.json.*not valid JSON"):
        RawTokenDataset(tmp_path, 2)
    (tmp_path / "metadata.json").write_text("[1, 2]")
    with pytest.raises(TokenDatasetError, match="metadata.json.*JSON object"):
        read_metadata(tmp_path)


@pytest.mark.parametrize("key", ["num_images", "s", "vocab_size", "hz"])
def test_missing_required_key(tmp_path, key):
    make_dataset(tmp_path)
    edit_metadata(tmp_path, **{key: None})
    with pytest.raises(TokenDatasetError, match=f"metadata.json.*missing.*{key}"):
        RawTokenDataset(tmp_path, 2)


@pytest.mark.parametrize("key,value", [
    ("num_images", "40"), ("num_images", 40.0), ("num_images", True), ("num_images", -40), ("num_images", 0),
    ("num_images", 2 ** 60), ("s", 0), ("s", -2), ("s", [2]), ("s", 10 ** 6), ("vocab_size", 0),
    ("vocab_size", 2 ** 80), ("vocab_size", None), ("hz", 0), ("hz", -30), ("hz", "30"), ("hz", float("nan")),
    ("hz", 1e9), ("token_dtype", "float32"), ("token_dtype", "uint24"), ("token_dtype", 4), ("h", 3),
])
def test_bad_metadata_values(tmp_path, key, value):
    make_dataset(tmp_path)
    edit_metadata(tmp_path, **{key: value})
    with pytest.raises(TokenDatasetError, match=f"metadata.json.*'?{key}'?"):
        RawTokenDataset(tmp_path, 2)


@pytest.mark.parametrize("delta", [-1, -16, 4, 1000])
def test_video_size_mismatch(tmp_path, delta):
    make_dataset(tmp_path, n=40, s=2)
    expected = 40 * 2 * 2 * 4
    with open(tmp_path / "video.bin", "r+b") as f:
        f.truncate(expected + delta)
    with pytest.raises(TokenDatasetError, match=f"video.bin: expected {expected} bytes.*found {expected + delta} "
                                                f"bytes.*truncated or corrupt"):
        RawTokenDataset(tmp_path, 2)


def test_token_dtype_uint16(tmp_path):
    video = make_dataset(tmp_path, n=12, token_dtype="uint16")
    assert (tmp_path / "video.bin").stat().st_size == 12 * 4 * 2
    ds = RawTokenDataset(tmp_path, 3)
    assert torch.equal(ds[0]["tokens"], torch.from_numpy(video[:3]).long())


def test_segment_ids_bad(tmp_path):
    make_dataset(tmp_path, n=20, segment_ids=np.arange(20) // 5)
    seg_path = tmp_path / "segment_ids.bin"
    seg = np.fromfile(seg_path, dtype=np.int32)
    seg[:19].tofile(seg_path)
    with pytest.raises(TokenDatasetError, match="segment_ids.bin: expected 80 bytes.*found 76"):
        RawTokenDataset(tmp_path, 2)
    seg[13] = 0
    seg.tofile(seg_path)
    with pytest.raises(TokenDatasetError, match=r"segment_ids.bin.*non-decreasing.*segment_ids\[13\] = 0 < "
                                                r"segment_ids\[12\] = 2"):
        RawTokenDataset(tmp_path, 2, filter_interrupts=False)


def test_segments_too_short(tmp_path):
    make_dataset(tmp_path, n=20, segment_ids=np.arange(20) // 4)
    RawTokenDataset(tmp_path, 4)
    with pytest.raises(TokenDatasetError, match="segment_ids.bin.*no segment is long enough"):
        RawTokenDataset(tmp_path, 5)


@pytest.mark.parametrize("window_size,stride", [(0, 1), (-3, 1), (2, 0), (2, -1), (2.0, 1), (2, True)])
def test_bad_window_args(tmp_path, window_size, stride):
    make_dataset(tmp_path)
    with pytest.raises(TokenDatasetError, match=str(tmp_path)):
        RawTokenDataset(tmp_path, window_size, stride)


def test_window_longer_than_data(tmp_path):
    make_dataset(tmp_path, n=20)
    RawTokenDataset(tmp_path, window_size=4, stride=6)  # needs 19 frames
    with pytest.raises(TokenDatasetError, match="video.bin.*needs 22 frames but the dataset has 20"):
        RawTokenDataset(tmp_path, window_size=4, stride=7, filter_interrupts=False)


@pytest.mark.parametrize("size", [0, 3, 20 * 4 + 1, 20 * 4 * 2 + 4])
def test_action_file_bad_size(tmp_path, size):
    make_dataset(tmp_path, n=20)
    (tmp_path / "actions").mkdir()
    (tmp_path / "actions" / "joint_pos.bin").write_bytes(b"\0" * size)
    with pytest.raises(TokenDatasetError, match="joint_pos.bin.*num_images=20 x k x 4"):
        RawTokenDataset(tmp_path, 2)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_actions(tmp_path, monkeypatch, bad):
    actions = np.zeros((20, 2))
    make_dataset(tmp_path, n=20, actions={"cmd": actions})
    actions[13, 1] = bad
    actions.astype(np.float32).tofile(tmp_path / "actions" / "cmd.bin")
    with pytest.raises(TokenDatasetError, match="cmd.bin.*non-finite.*frame 13"):
        RawTokenDataset(tmp_path, 2)
    # Big files are only checked window by window (and by validate()).
    monkeypatch.setattr(token_dataset, "SMALL_FILE_BYTES", 0)
    ds = RawTokenDataset(tmp_path, 2)
    ds[11]
    with pytest.raises(TokenDatasetError, match="cmd.bin.*non-finite.*frame 13"):
        ds[12]
    with pytest.raises(TokenDatasetError, match="cmd.bin.*frame 13"):
        ds.validate()


def test_token_out_of_vocab(tmp_path):
    video = make_dataset(tmp_path, n=20, vocab_size=16)
    video[9, 1, 0] = 16
    video.astype(np.uint32).tofile(tmp_path / "video.bin")
    ds = RawTokenDataset(tmp_path, window_size=3, stride=2)
    ds[0]
    with pytest.raises(TokenDatasetError, match=r"video.bin: token id 16 at frame 9 \(row 1, column 0\).*"
                                                r"vocab_size=16"):
        ds[5]
    unchecked = RawTokenDataset(tmp_path, window_size=3, stride=2, check_tokens=False)
    assert unchecked[5]["tokens"].max() == 16
    with pytest.raises(TokenDatasetError, match="video.bin: token id 16 at frame 9"):
        ds.validate(full=True)


def test_validate_full_scans_frames_outside_windows(tmp_path):
    video = make_dataset(tmp_path, n=20, vocab_size=16, segment_ids=np.arange(20) // 10)
    video[6, 0, 0] = 99  # windows of frames (0, 4, 8), (1, 5, 9), (10, 14, 18), (11, 15, 19) miss frame 6
    video.astype(np.uint32).tofile(tmp_path / "video.bin")
    ds = RawTokenDataset(tmp_path, window_size=3, stride=4)
    assert ds.valid_start_inds.tolist() == [0, 1, 10, 11]
    for i in range(len(ds)):
        ds[i]
    ds.validate(full=False)
    with pytest.raises(TokenDatasetError, match="token id 99 at frame 6"):
        ds.validate(full=True)


# ---------------------------------------------------------------- writer

def test_writer_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    video = rng.integers(0, 262144, (30, 4, 4))
    seg = np.repeat([3, 5, 6], 10)
    actions = {"driving_command": rng.normal(size=(30, 2)), "neck_desired": rng.normal(size=(30, 1))}
    out = write_token_dataset(tmp_path / "ds", video, seg, actions, metadata={"hz": 10, "extra": "kept"})
    assert out == tmp_path / "ds"
    meta = json.loads((out / "metadata.json").read_text())
    assert meta == {"token_dtype": "uint32", "vocab_size": 262144, "hz": 10, "extra": "kept", "s": 4, "h": 4,
                    "w": 4, "num_images": 30}
    np.testing.assert_array_equal(np.fromfile(out / "video.bin", dtype="<u4").reshape(30, 4, 4), video)
    np.testing.assert_array_equal(np.fromfile(out / "segment_ids.bin", dtype="<i4"), seg)
    np.testing.assert_array_equal(np.fromfile(out / "actions" / "neck_desired.bin", dtype="<f4"),
                                  actions["neck_desired"][:, 0].astype(np.float32))
    ds = RawTokenDataset(out, window_size=10)
    assert len(ds) == 3 and ds.action_names == ["driving_command", "neck_desired"]
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]  # no temp dirs left behind


def test_streaming_writer_equals_one_shot(tmp_path):
    rng = np.random.default_rng(2)
    video = rng.integers(0, 50, (25, 2, 2))
    seg = np.repeat(np.arange(5), 5)
    actions = rng.normal(size=(25, 3))
    write_token_dataset(tmp_path / "one", video, seg, {"a": actions}, metadata={"vocab_size": 50})
    with TokenDatasetWriter(tmp_path / "many", s=2, metadata={"vocab_size": 50}) as writer:
        for a, b in [(0, 7), (7, 7), (7, 20), (20, 25)]:
            writer.append(video[a:b], seg[a:b], {"a": actions[a:b]})
    for name in ("metadata.json", "video.bin", "segment_ids.bin", "actions/a.bin"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "many" / name).read_bytes()


def test_writer_exception_leaves_nothing(tmp_path):
    video = np.zeros((5, 2, 2), dtype=np.int64)
    with pytest.raises(RuntimeError, match="boom"):
        with TokenDatasetWriter(tmp_path / "ds", s=2) as writer:
            writer.append(video, np.zeros(5, dtype=int))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    # A failing replacement leaves the existing dataset untouched.
    write_token_dataset(tmp_path / "ds", video + 1)
    with pytest.raises(RuntimeError, match="boom"):
        with TokenDatasetWriter(tmp_path / "ds", s=2, overwrite=True) as writer:
            writer.append(video, None)
            raise RuntimeError("boom")
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]
    assert RawTokenDataset(tmp_path / "ds", 1)[0]["tokens"].flatten().tolist() == [1, 1, 1, 1]


def test_writer_overwrite(tmp_path):
    write_token_dataset(tmp_path / "ds", np.ones((5, 2, 2), dtype=int))
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_token_dataset(tmp_path / "ds", np.zeros((6, 2, 2), dtype=int))
    assert read_metadata(tmp_path / "ds")["num_images"] == 5
    write_token_dataset(tmp_path / "ds", np.zeros((6, 3, 3), dtype=int), overwrite=True)
    assert read_metadata(tmp_path / "ds")["num_images"] == 6
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]
    (tmp_path / "empty").mkdir()
    write_token_dataset(tmp_path / "empty", np.zeros((2, 2, 2), dtype=int))
    assert read_metadata(tmp_path / "empty")["num_images"] == 2


@pytest.mark.parametrize("video,kwargs,match", [
    (np.full((3, 2, 2), 16), {"metadata": {"vocab_size": 16}}, r"\[0, 16\)"),
    (np.full((3, 2, 2), -1), {}, r"range \[-1, -1\]"),
    (np.full((3, 2, 2), 70000), {"metadata": {"token_dtype": "uint16"}}, r"\[0, 65536\).*uint16"),
    (np.zeros((3, 2, 2), dtype=np.float32), {}, "integers"),
    (np.zeros((3, 2, 3), dtype=int), {}, "shape"),
    (np.zeros((3, 2, 2), dtype=int), {"segment_ids": [0, 2, 1]}, "non-decreasing"),
    (np.zeros((3, 2, 2), dtype=int), {"segment_ids": [0, 1]}, "segment_ids"),
    (np.zeros((3, 2, 2), dtype=int), {"actions": {"a": [[0.0], [np.nan], [1.0]]}}, "NaN"),
    (np.zeros((3, 2, 2), dtype=int), {"actions": {"a": [0.0, 1.0, 2.0]}}, r"shape \(3, k\)"),
    (np.zeros((3, 2, 2), dtype=int), {"actions": {"../a": np.zeros((3, 1))}}, "file name"),
    (np.zeros((3, 2, 2), dtype=int), {"actions": {"a": np.full((3, 1), 1e39)}}, "float32"),
    (np.zeros((3, 2, 2), dtype=int), {"metadata": {"num_images": 3}}, "num_images"),
    (np.zeros((3, 2, 2), dtype=int), {"metadata": {"s": 3}}, "conflicts"),
    (np.zeros((3, 2, 2), dtype=int), {"metadata": {"hz": -1}}, "hz"),
    (np.zeros((0, 2, 2), dtype=int), {}, "no frames"),
])
def test_writer_refuses_bad_input(tmp_path, video, kwargs, match):
    with pytest.raises(TokenDatasetError, match=match):
        write_token_dataset(tmp_path / "ds", video, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_writer_checks_across_chunks(tmp_path):
    video = np.zeros((4, 2, 2), dtype=int)
    with pytest.raises(TokenDatasetError, match="non-decreasing"):
        with TokenDatasetWriter(tmp_path / "ds", s=2) as writer:
            writer.append(video, [0, 1, 2, 3])
            writer.append(video, [2, 4, 5, 6])
    with pytest.raises(TokenDatasetError, match="differ from those of the first chunk"):
        with TokenDatasetWriter(tmp_path / "ds", s=2) as writer:
            writer.append(video, None, {"a": np.zeros((4, 2))})
            writer.append(video, None, {"a": np.zeros((4, 3))})
    assert list(tmp_path.iterdir()) == []
