"""visualize.py: token dirs -> GIF (+ comic PNG) decoded with a tokenizer checkpoint."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import visualize
from common.cli import run_main
from common.errors import InputError
from data import write_token_dataset
from magvit2 import VQConfig, VQModel

REPO = Path(__file__).resolve().parents[1]
SIDE = 16  # image side of the tiny tokenizer (8x8 tokens)
SHOWN = SIDE * visualize.display_scale(SIDE)  # small frames are zoomed in the GIF


@pytest.fixture(scope="module")
def tokenizer_dir(tmp_path_factory):
    torch.manual_seed(0)
    model = VQModel(VQConfig(base_channels=32, ch_mult=[1, 2], num_res_blocks=1, z_channels=6, codebook_size=64,
                             resolution=SIDE))
    path = tmp_path_factory.mktemp("tok") / "tokenizer"
    model.save_pretrained(path)
    return path


def random_tokens(n, seed=0):
    return np.random.default_rng(seed).integers(0, 64, (n, SIDE // 2, SIDE // 2))


def test_generated_dir_gives_captioned_gif_and_comic(tmp_path, tokenizer_dir):
    P, W, examples = 2, 4, 2
    token_dir = tmp_path / "generated"
    write_token_dataset(token_dir, random_tokens(examples * (2 * W - P)),
                        metadata={"vocab_size": 64, "num_prompt_frames": P, "window_size": W})
    result = subprocess.run([sys.executable, str(REPO / "visualize.py"), "--token_dir", str(token_dir),
                             "--tokenizer_ckpt", str(tokenizer_dir), "--device", "cpu", "--output_dir",
                             str(tmp_path / "out")], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr
    with Image.open(tmp_path / "out" / "generated_offset0.gif") as gif:
        assert gif.n_frames == W
        # one row per example: model frame | ground truth, each with a caption strip above
        assert gif.size == (2 * SHOWN, examples * (SHOWN + visualize.CAPTION_HEIGHT))
    with Image.open(tmp_path / "out" / "generated_comic_offset0.png") as comic:
        comic.load()
        assert comic.format == "PNG" and np.asarray(comic.convert("L")).std() > 10  # not a blank canvas
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]  # no temp files left


def test_plain_dataset_gif_with_labels_and_metadata_checkpoint(tmp_path, tokenizer_dir, monkeypatch):
    token_dir = tmp_path / "dataset"
    tokens = random_tokens(10, seed=1)
    write_token_dataset(token_dir, tokens, metadata={"vocab_size": 64, "tokenizer_ckpt": str(tokenizer_dir)})
    (tmp_path / "labels.json").write_text(json.dumps([f"a{i}" for i in range(10)]))
    monkeypatch.chdir(tmp_path)
    visualize.main(["--token_dir", str(token_dir), "--offset", "1", "--stride", "3", "--device", "cpu",
                    "--labels", str(tmp_path / "labels.json")])
    with Image.open(token_dir / "generated_offset1.gif") as gif:
        assert gif.n_frames == 3  # frames 1, 4, 7
        assert gif.size == (SHOWN, SHOWN + visualize.LABEL_HEIGHT)
        gif.seek(0)
        first = np.asarray(gif.convert("RGB"))
    assert not (token_dir / "generated_comic_offset1.png").exists()
    # the frame shown is frame 1 decoded (GIF palettes are lossy: compare loosely)
    decoded = VQModel.from_checkpoint(tokenizer_dir).eval().tokens_to_images(tokens[1:2])[0]
    zoom = SHOWN // SIDE
    assert np.abs(first[:SHOWN:zoom, ::zoom].astype(int) - decoded.astype(int)).mean() < 12


def test_frames_labelled_with_an_action_stream(tmp_path, tokenizer_dir):
    token_dir = tmp_path / "dataset"
    tokens = np.repeat(random_tokens(1, seed=2), 4, axis=0)  # identical frames: only the labels differ
    write_token_dataset(token_dir, tokens, actions={"latent_action": np.array([[0], [7], [123], [7]])},
                        metadata={"vocab_size": 64})
    args = ["--token_dir", str(token_dir), "--tokenizer_ckpt", str(tokenizer_dir), "--device", "cpu"]
    visualize.main(args + ["--label_action", "latent_action"])
    strips = []
    with Image.open(token_dir / "generated_offset0.gif") as gif:
        for i in range(gif.n_frames):
            gif.seek(i)
            strips.append(np.asarray(gif.convert("L"))[SHOWN:])
    assert len(strips) == 4
    assert np.array_equal(strips[1], strips[3])  # same label, same text
    assert not np.array_equal(strips[0], strips[1]) and not np.array_equal(strips[1], strips[2])
    with pytest.raises(InputError, match="nope.bin.*latent_action"):
        visualize.main(args + ["--label_action", "nope"])


def test_missing_checkpoint_error_names_the_options(tmp_path, monkeypatch, capsys):
    token_dir = tmp_path / "dataset"
    write_token_dataset(token_dir, random_tokens(3), metadata={"vocab_size": 64, "tokenizer_ckpt": "gone.ckpt"})
    monkeypatch.chdir(tmp_path)  # no data/magvit2.ckpt here
    assert run_main("visualize.py", visualize.main, ["--token_dir", str(token_dir), "--device", "cpu"]) == 1
    message = capsys.readouterr().err.splitlines()[-1]  # one line, no traceback
    assert message.startswith("visualize.py: error: ")
    assert "--tokenizer_ckpt" in message and "gone.ckpt" in message and "data/magvit2.ckpt" in message


def test_labels_must_cover_every_frame(tmp_path):
    (tmp_path / "labels.txt").write_text("a\nb\n")
    with pytest.raises(ValueError, match="2 labels.*3 frames"):
        visualize.load_labels(tmp_path / "labels.txt", 3)
