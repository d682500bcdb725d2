"""Integrity and disk faults: recorded digests refuse corrupted files; a full disk ends in one clear line and loses
nothing (common/integrity.py, common/errors.py WriteError)."""
import errno
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors import SafetensorError

import train
import visualize
from common.errors import IntegrityError, WriteError
from common.files import write_json_atomic
from common.integrity import MANIFEST_NAME, read_manifest, verify_manifest
from common.train_state import list_checkpoints, load_training_checkpoint, save_training_checkpoint
from data import RawTokenDataset, TokenDatasetError, TokenDatasetWriter
from data import verify as data_verify
from genie.config import GenieConfig
from training.masking import MaskGITBatch
from genie.model import STMaskGIT
from lam.model import LAM, LAMConfig
from magvit2 import VQModel
from tests.test_lam import TINY as TINY_LAM
from tests.test_magvit2_model import tiny_config
from tests.test_train import TINY, make_token_dataset, train_argv, write_config

REPO = Path(__file__).resolve().parents[1]
ENOSPC = OSError(errno.ENOSPC, "No space left on device")

pytestmark = pytest.mark.usefixtures("one_thread")


def flip_byte(path: Path, offset=None) -> None:
    """Flip one bit of one byte (the middle one by default): same size, different contents."""
    data = bytearray(path.read_bytes())
    i = len(data) // 2 if offset is None else offset
    data[i] ^= 0x01
    path.write_bytes(bytes(data))


def tiny_genie() -> STMaskGIT:
    torch.manual_seed(0)
    return STMaskGIT(GenieConfig.from_dict(dict(TINY)))


# ---------------------------------------------------------------- corrupted files are refused

def test_flipped_byte_in_genie_weights_is_refused_naming_the_file(tmp_path):
    tiny_genie().save_pretrained(tmp_path / "model")
    assert set(read_manifest(tmp_path / "model")) == {"config.json", "decoding.json", "model.safetensors"}
    STMaskGIT.from_pretrained(tmp_path / "model")  # intact: loads
    flip_byte(tmp_path / "model" / "model.safetensors")
    with pytest.raises(IntegrityError, match=r"model\.safetensors.*do not match the digest"):
        STMaskGIT.from_pretrained(tmp_path / "model")


def test_checkpoint_without_manifest_loads_as_before(tmp_path):
    """Published checkpoints have no MANIFEST.json: nothing to verify, they load as before."""
    tiny_genie().save_pretrained(tmp_path / "model")
    (tmp_path / "model" / MANIFEST_NAME).unlink()
    STMaskGIT.from_pretrained(tmp_path / "model")
    assert verify_manifest(tmp_path / "model") == []


def test_saving_over_an_existing_model_keeps_its_manifest_valid(tmp_path):
    tiny_genie().save_pretrained(tmp_path / "model")
    model = tiny_genie()
    with torch.no_grad():
        next(model.parameters()).add_(1.0)
    model.save_pretrained(tmp_path / "model")  # replaces the files in place
    assert verify_manifest(tmp_path / "model") == ["config.json", "decoding.json", "model.safetensors"]


def test_flipped_byte_in_training_checkpoint_is_refused_on_resume(tmp_path):
    model = tiny_genie()
    optimizer = torch.optim.AdamW(model.parameters())
    x = torch.randint(0, 4096, (1, 4, 4, 4))
    model(MaskGITBatch(x.masked_fill(torch.rand(x.shape) < 0.5, 4096), x)).loss.backward()
    optimizer.step()
    ckpt = tmp_path / "checkpoint-1"
    save_training_checkpoint(ckpt, model, optimizer, {"step": 1}, [{"seed": 0}])
    assert set(read_manifest(ckpt)) >= {"model.safetensors", "optimizer.safetensors", "trainer_state.json"}
    load_training_checkpoint(ckpt)
    flip_byte(ckpt / "optimizer.safetensors")
    with pytest.raises(IntegrityError, match=r"optimizer\.safetensors"):
        load_training_checkpoint(ckpt)


def test_flipped_byte_in_tokenizer_checkpoint_is_refused(tmp_path):
    VQModel(tiny_config()).save_pretrained(tmp_path / "tok")
    VQModel.from_checkpoint(tmp_path / "tok")
    flip_byte(tmp_path / "tok" / "model.safetensors")
    with pytest.raises(IntegrityError, match=r"tok/model\.safetensors"):
        VQModel.from_checkpoint(tmp_path / "tok")


def test_flipped_byte_in_lam_is_refused(tmp_path):
    LAM(LAMConfig(**TINY_LAM)).save_pretrained(tmp_path / "lam")
    LAM.from_pretrained(tmp_path / "lam")
    flip_byte(tmp_path / "lam" / "model.safetensors")
    with pytest.raises(IntegrityError, match=r"lam/model\.safetensors"):
        LAM.from_pretrained(tmp_path / "lam")


def test_token_dataset_digests_are_verified_on_demand(tmp_path, capsys):
    data_dir = make_token_dataset(tmp_path / "ds", [8] * 4)
    assert set(read_manifest(data_dir)) == {"metadata.json", "segment_ids.bin", "video.bin"}
    data_verify.main([str(data_dir)])
    assert "OK" in capsys.readouterr().out
    flip_byte(data_dir / "video.bin", offset=1)  # a low-order byte: the token id stays in range
    ds = RawTokenDataset(data_dir, window_size=4)  # opening does not hash video.bin
    ds.validate(full=False)
    with pytest.raises(TokenDatasetError, match=r"video\.bin.*corrupt"):
        ds.validate(full=True)
    with pytest.raises(IntegrityError, match="1 problem"):
        data_verify.main([str(data_dir)])
    out = capsys.readouterr().out
    assert "FAILED" in out and "video.bin" in out and "OK" in out  # the intact files are listed as OK


def test_dataset_without_manifest_verifies_sizes_only(tmp_path, capsys):
    data_dir = make_token_dataset(tmp_path / "ds", [8] * 4)
    (data_dir / MANIFEST_NAME).unlink()
    RawTokenDataset(data_dir, window_size=4).validate(full=True)
    data_verify.main([str(data_dir)])
    assert "sizes checked only" in capsys.readouterr().out


# ---------------------------------------------------------------- a full disk: one clear line, nothing lost

def test_full_disk_during_training_checkpoint_names_the_last_complete_one(tmp_path, monkeypatch, capsys):
    """The second checkpoint fails with safetensors' own ENOSPC error: one line, checkpoint-2 kept and resumable."""
    import common.train_state
    root = tmp_path / "data"
    data = {"train": make_token_dataset(root / "train", [8] * 12, seed=0),
            "val": make_token_dataset(root / "val", [8] * 3, seed=1), "config": write_config(root / "tiny.json")}
    out = tmp_path / "run"
    real_save_file = common.train_state.save_file

    def save_file(tensors, path, *args, **kwargs):
        if "checkpoint-4" in path:
            raise SafetensorError("Error while serializing: IoError(No space left on device (os error 28))")
        return real_save_file(tensors, path, *args, **kwargs)

    monkeypatch.setattr(common.train_state, "save_file", save_file)
    argv = train_argv(data, out, "--max_train_steps", "6", "--checkpointing_steps", "2",
                      "--checkpoints_total_limit", "1")
    with pytest.raises(SystemExit) as exc:
        train.main(argv)
    message = str(exc.value.code)
    assert message.count("\n") == 0
    assert f"could not write the training checkpoint to {out / 'checkpoint-4'}: No space left on device" in message
    assert f"last complete checkpoint: {out / 'checkpoint-2'} (resume with --resume_from_checkpoint latest)" in message
    assert "Traceback" not in capsys.readouterr().err
    assert [step for step, _ in list_checkpoints(out)] == [2]  # not pruned: the new one never completed
    assert sorted(p.name for p in out.iterdir() if p.name.startswith("checkpoint")) == ["checkpoint-2"]
    assert not list(out.glob(".tmp-*"))

    monkeypatch.setattr(common.train_state, "save_file", real_save_file)  # space freed: resume finishes the run
    train.main(argv + ["--resume_from_checkpoint", "latest"])
    assert [step for step, _ in list_checkpoints(out)] == [6]
    STMaskGIT.from_pretrained(out / "final_checkpt")


def test_full_disk_while_writing_a_dataset_keeps_the_previous_one(tmp_path, monkeypatch):
    import data.token_dataset
    out = make_token_dataset(tmp_path / "ds", [8] * 4)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def fail(*args, **kwargs):
        raise ENOSPC

    monkeypatch.setattr(data.token_dataset, "update_manifest", fail)
    with pytest.raises(WriteError, match=f"could not write the token dataset to {out}: No space left on device"):
        with TokenDatasetWriter(out, 4, overwrite=True) as writer:
            writer.append(np.zeros((8, 4, 4), dtype=np.int64))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]  # no temp directory left behind


def test_file_size_limit_while_writing_a_dataset_is_one_line(tmp_path):
    """A real OS-level write failure (RLIMIT_FSIZE -> EFBIG) in a child process: one line, exit 1, no dataset."""
    out = tmp_path / "ds"
    code = (f"import resource, signal, sys, numpy as np\n"
            f"signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            f"resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, resource.RLIM_INFINITY))\n"
            f"from common.errors import WriteError\n"
            f"from data import write_token_dataset\n"
            f"try:\n"
            f"    write_token_dataset({str(out)!r}, np.zeros((2000, 16, 16), dtype=np.int64))\n"
            f"except WriteError as e:\n"
            f"    sys.exit(f'error: {{e}}')\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"error: could not write the token dataset to {out}: File too large"]
    assert list(tmp_path.iterdir()) == []


def test_full_disk_while_writing_a_gif_or_metrics_keeps_the_old_file(tmp_path, monkeypatch):
    gif = tmp_path / "out.gif"
    frames = [Image.new("RGB", (8, 8), (i * 40, 0, 0)) for i in range(3)]
    visualize.save_gif(frames, gif, fps=5)
    old_gif = gif.read_bytes()
    write_json_atomic(tmp_path / "metrics.json", {"val_loss": 1.0})

    def fail(*args, **kwargs):
        raise ENOSPC

    monkeypatch.setattr(Image.Image, "save", fail)
    with pytest.raises(WriteError, match=f"could not write the GIF to {gif}: No space left on device"):
        visualize.save_gif(frames, gif, fps=5)
    monkeypatch.setattr(Path, "write_text", fail)
    with pytest.raises(WriteError, match=r"could not write the evaluation results to .*metrics\.json: No space"):
        write_json_atomic(tmp_path / "metrics.json", {"val_loss": 2.0}, "the evaluation results")
    assert gif.read_bytes() == old_gif
    assert json.loads((tmp_path / "metrics.json").read_text()) == {"val_loss": 1.0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json", "out.gif"]  # no temp files left


def test_other_errors_are_not_disguised_as_write_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        write_json_atomic(tmp_path / "missing_dir" / "x.json", {})
