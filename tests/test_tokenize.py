"""magvit2.tokenize_frames: frames + actions + segment ids -> token dataset that data.RawTokenDataset reads back."""
import json
import os

import numpy as np
import pytest
import torch
from PIL import Image

from data import RawTokenDataset
from magvit2 import VQConfig, VQModel
from magvit2.tokenize_frames import TokenizeInputError, main, tokenize_frames


@pytest.fixture(scope="module")
def tokenizer_dir(tmp_path_factory):
    torch.manual_seed(0)
    model = VQModel(VQConfig(base_channels=32, ch_mult=[1, 2], num_res_blocks=1, z_channels=6, codebook_size=64,
                             resolution=16))
    with torch.no_grad():  # non-trivial GroupNorm affine weights so tokens depend on the image
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    path = tmp_path_factory.mktemp("tok") / "tokenizer"
    model.save_pretrained(path)
    return path


def frames(n, seed, side=16):
    return np.random.default_rng(seed).integers(0, 256, (n, side, side, 3), dtype=np.uint8)


def test_npz_episodes_round_trip(tmp_path, tokenizer_dir):
    a, b = frames(7, 1), frames(4, 2)
    np.savez(tmp_path / "ep_a.npz", frames=a, segment_ids=np.array([3, 3, 3, 5, 5, 9, 9]),
             actions_joint_pos=np.arange(21.0 * 7).reshape(7, 21), actions_gripper=np.linspace(0, 1, 7), hz=10)
    np.savez(tmp_path / "ep_b.npz", frames=b, actions_joint_pos=np.ones((4, 21)), actions_gripper=np.zeros(4),
             hz=10)
    out = tmp_path / "tokens"
    main([str(tmp_path / "ep_a.npz"), str(tmp_path / "ep_b.npz"), "--tokenizer_ckpt", str(tokenizer_dir),
          "--output_dir", str(out), "--batch_size", "3", "--device", "cpu"])

    model = VQModel.from_checkpoint(tokenizer_dir).eval()
    ds = RawTokenDataset(out, window_size=2, stride=1)
    expected = np.concatenate([model.images_to_tokens(a), model.images_to_tokens(b)])
    assert np.array_equal(np.asarray(ds.data), expected)
    # segment ids are kept for the first file; the second file continues after its last one
    assert np.array_equal(np.asarray(ds.segment_ids), [3, 3, 3, 5, 5, 9, 9, 10, 10, 10, 10])
    assert ds.action_names == ["gripper", "joint_pos"]
    assert np.array_equal(ds.actions["joint_pos"][:7], np.arange(21.0 * 7).reshape(7, 21))
    assert np.allclose(ds.actions["gripper"][:, 0], np.r_[np.linspace(0, 1, 7), np.zeros(4)])
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["tokenizer_ckpt"] == str(tokenizer_dir)
    assert (meta["num_images"], meta["s"], meta["vocab_size"], meta["hz"]) == (11, 8, 64, 10)
    # windows never cross segments
    assert len(ds) == 2 + 1 + 1 + 3

    with pytest.raises(TokenizeInputError, match="--overwrite"):
        main([str(tmp_path / "ep_b.npz"), "--tokenizer_ckpt", str(tokenizer_dir), "--output_dir", str(out),
              "--device", "cpu"])
    main([str(tmp_path / "ep_b.npz"), "--tokenizer_ckpt", str(tokenizer_dir), "--output_dir", str(out),
          "--device", "cpu", "--overwrite"])
    assert RawTokenDataset(out, window_size=1).metadata["num_images"] == 4


def test_image_folder_in_natural_order_with_resize(tmp_path, tokenizer_dir):
    images = frames(11, 3, side=24)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, image in enumerate(images):
        Image.fromarray(image).save(folder / f"frame_{i}.png")  # frame_10 sorts after frame_9
    out = tmp_path / "tokens"
    main([str(folder), "--tokenizer_ckpt", str(tokenizer_dir), "--output_dir", str(out), "--device", "cpu",
          "--image_size", "16"])
    model = VQModel.from_checkpoint(tokenizer_dir).eval()
    resized = np.stack([np.asarray(Image.fromarray(im).resize((16, 16), Image.Resampling.BICUBIC)) for im in images])
    ds = RawTokenDataset(out, window_size=1)
    assert np.array_equal(np.asarray(ds.data), model.images_to_tokens(resized))
    assert set(np.asarray(ds.segment_ids)) == {0} and ds.metadata["hz"] == 30


def test_inconsistent_inputs_are_errors_naming_the_file(tmp_path, tokenizer_dir):
    np.savez(tmp_path / "a.npz", frames=frames(3, 4), actions_x=np.zeros((3, 2)))
    np.savez(tmp_path / "b.npz", frames=frames(3, 5), actions_y=np.zeros((3, 2)))
    np.savez(tmp_path / "odd.npz", frames=frames(3, 6, side=15))
    base = ["--tokenizer_ckpt", str(tokenizer_dir), "--device", "cpu"]
    with pytest.raises(TokenizeInputError, match="b.npz.*actions"):
        main([str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--output_dir", str(tmp_path / "o1"), *base])
    with pytest.raises(TokenizeInputError, match="odd.npz.*not divisible"):
        main([str(tmp_path / "odd.npz"), "--output_dir", str(tmp_path / "o2"), *base])
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_tokenize_frames_in_memory(tmp_path, tokenizer_dir):
    model = VQModel.from_checkpoint(tokenizer_dir).eval()
    video = frames(5, 7)
    out = tokenize_frames(model, video, tmp_path / "mem", tokenizer_ckpt="my_tok", segment_ids=[0, 0, 1, 1, 1],
                          actions={"cmd": np.ones((5, 2))}, hz=15, progress=False)
    ds = RawTokenDataset(out, window_size=2)
    assert np.array_equal(np.asarray(ds.data), model.images_to_tokens(video))
    assert len(ds) == 1 + 2 and ds.metadata["hz"] == 15 and ds.metadata["tokenizer_ckpt"] == "my_tok"


def test_build_sample_tokenizes_a_split_once(tmp_path, tokenizer_dir, capsys):
    """build_sample's tokenize_split: the split's frames become its tokens, with segments and actions; a second build
    is a no-op, and new raw frames are tokenized again."""
    from sample_world.build import tokenize_split

    n = 6
    raw = tmp_path / "train.npz"
    np.savez(raw, frames=frames(n, 3), segment_ids=np.array([0, 0, 0, 1, 1, 1], np.int32),
             actions_buttons=np.eye(n, 5, dtype=np.float32), hz=np.int32(35))
    out = tmp_path / "train"
    tokenize_split([raw], out, tokenizer_dir, "tiny", batch_size=4, device="cpu", overwrite=False)
    model = VQModel.from_checkpoint(tokenizer_dir).eval()
    video = np.fromfile(out / "video.bin", dtype=np.uint32).reshape(n, -1)
    with np.load(raw) as npz:
        np.testing.assert_array_equal(video, np.asarray(model.images_to_tokens(npz["frames"])).reshape(n, -1))
    assert np.fromfile(out / "segment_ids.bin", dtype=np.int32).tolist() == [0, 0, 0, 1, 1, 1]
    buttons = np.fromfile(out / "actions" / "buttons.bin", dtype=np.float32).reshape(n, 5)
    np.testing.assert_array_equal(buttons, np.eye(n, 5))

    capsys.readouterr()
    tokenize_split([raw], out, tokenizer_dir, "tiny", batch_size=4, device="cpu", overwrite=False)
    assert "up to date" in capsys.readouterr().out
    np.savez(raw, frames=frames(n, 4), segment_ids=np.zeros(n, np.int32), hz=np.int32(35))
    os.utime(raw, (1, 1))  # another mtime, whatever the clock's resolution
    tokenize_split([raw], out, tokenizer_dir, "tiny", batch_size=4, device="cpu", overwrite=False)
    assert "tokenized" in capsys.readouterr().out
    assert np.fromfile(out / "segment_ids.bin", dtype=np.int32).tolist() == [0] * n
