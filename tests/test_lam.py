"""Latent action model: shapes, VQ mechanics, learning a hidden action, checkpoints, probe, and the two CLIs."""
import json
import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lam import label as label_latent_actions, train as train_lam
from lam.probe import action_probe, button_combination_ids, combination_name, transition_labels
from common.cli import run_main
from common.config import ConfigError
from common.images import psnr
from lam.model import LAM, LAMConfig, VectorQuantizer, local_correlation
from lam.data import gather_transitions, valid_targets

TINY = dict(image_size=16, channels=[8, 16], latent_dim=8, codebook_size=8, dead_code_steps=20)
SHIFTS = [(0, -2), (0, 2), (-2, 0), (2, 0)]  # the hidden action: roll the image left / right / up / down


pytestmark = pytest.mark.usefixtures("one_thread")


def shifted_pairs(gen: torch.Generator, batch: int, size: int = 16):
    """Smooth random textures and the same textures rolled by a hidden action: past (B,1,3,H,W), next, action."""
    texture = F.interpolate(torch.rand(batch, 3, 4, 4, generator=gen) * 2 - 1, size=(size, size), mode="bilinear",
                            align_corners=False)
    action = torch.randint(0, len(SHIFTS), (batch,), generator=gen)
    nxt = torch.stack([torch.roll(t, SHIFTS[a], dims=(1, 2)) for t, a in zip(texture, action.tolist())])
    return texture[:, None], nxt, action


def test_shapes():
    cfg = LAMConfig(**{**TINY, "num_past_frames": 2})
    model = LAM(cfg)
    past, nxt = torch.rand(5, 2, 3, 16, 16) * 2 - 1, torch.rand(5, 3, 16, 16) * 2 - 1
    out = model(past, nxt)
    assert out.loss.ndim == 0 and torch.isfinite(out.loss)
    assert out.recon.shape == (5, 3, 16, 16)
    assert out.action_ids.shape == (5,) and out.action_ids.dtype == torch.int64
    assert out.z.shape == (5, cfg.latent_dim)
    assert 1.0 <= out.perplexity.item() <= cfg.codebook_size
    model.eval()
    ids = model.infer_actions(past, nxt)
    assert torch.equal(ids, model(past, nxt).action_ids)
    assert int(ids.min()) >= 0 and int(ids.max()) < cfg.codebook_size
    assert model.decode_with_actions(past, ids).shape == (5, 3, 16, 16)
    with pytest.raises(ValueError, match="past frames must have shape"):
        model(past[:, :1], nxt)
    with pytest.raises(ValueError, match=r"ids must be in \[0, 8\)"):
        model.decode_with_actions(past, torch.full((5,), 8))


def test_config_json_round_trip_and_errors():
    cfg = LAMConfig(**TINY)
    assert LAMConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ConfigError, match="unknown key"):
        LAMConfig.from_dict({**cfg.to_dict(), "codebook": 8})
    with pytest.raises(ConfigError, match="not divisible"):
        LAMConfig(image_size=20, channels=[8, 16, 32])
    with pytest.raises(ConfigError, match="codebook_size"):
        LAMConfig(codebook_size=1)
    with pytest.raises(ConfigError, match="lowres_pool"):
        LAMConfig(image_size=64, lowres_pool=6)


def test_reconstruction_sees_next_frame_only_through_the_code():
    torch.manual_seed(0)
    model = LAM(LAMConfig(**TINY)).eval()
    past, nxt = torch.rand(6, 1, 3, 16, 16) * 2 - 1, torch.rand(6, 3, 16, 16) * 2 - 1
    out = model(past, nxt)
    assert torch.allclose(out.recon, model.decode_with_actions(past, out.action_ids), atol=1e-6)


def test_local_correlation_peaks_at_the_displacement():
    radius = 3
    a = torch.randn(2, 16, 12, 12)
    b = torch.roll(a, shifts=(1, -2), dims=(2, 3))  # b[y + 1, x - 2] = a[y, x]
    corr = local_correlation(a, b, radius)
    assert corr.shape == (2, (2 * radius + 1) ** 2, 12, 12)
    best = corr[:, :, 3:-3, 3:-3].argmax(dim=1)  # positions whose whole window lies inside the map
    assert (best == (1 + radius) * (2 * radius + 1) + (-2 + radius)).all()


def test_vq_straight_through_gradient():
    vq = VectorQuantizer(codebook_size=4, dim=3, dead_code_steps=0)
    z = torch.randn(6, 3, requires_grad=True)
    out = vq(z)
    assert torch.allclose(out.z_q, vq.codebook[out.ids])  # forward value: the chosen codes
    weights = torch.randn(6, 3)
    (out.z_q * weights).sum().backward()
    assert torch.allclose(z.grad, weights)  # backward: the identity, straight through to the encoder output
    assert vq.codebook.grad is None  # the codes learn from the codebook loss only

    out = vq(z)
    out.loss.backward()
    used = torch.bincount(out.ids, minlength=4) > 0
    assert (vq.codebook.grad[used].abs().sum(dim=1) > 0).all()
    assert (vq.codebook.grad[~used] == 0).all()


def test_dead_code_restart_revives_unused_codes():
    torch.manual_seed(0)
    vq = VectorQuantizer(codebook_size=4, dim=2, dead_code_steps=3)
    vq.train()
    with torch.no_grad():
        vq.codebook.copy_(torch.tensor([[0.0, 0.0], [100.0, 100.0], [100.0, 101.0], [101.0, 100.0]]))
    vq.steps_since_used.zero_()  # as if trained: no code starts dead
    centers = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    z = centers.repeat(8, 1) + 0.01 * torch.randn(32, 2)
    for _ in range(3):  # codes 1..3 are too far to win any vector: unused for 3 steps
        out = vq(z)
        assert out.num_restarted == 0 and out.ids.unique().tolist() == [0]
    out = vq(z)
    assert out.num_restarted == 3
    assert len(out.ids.unique()) > 1
    restarted = vq.codebook.detach()[1:]
    gap_to_nearest_input = (restarted[:, None] - z[None]).abs().amax(dim=-1).min(dim=1).values
    assert gap_to_nearest_input.max() < 1e-6  # each restarted code is one of the encoder outputs

    vq.eval()
    vq.steps_since_used.fill_(10)
    before = vq.codebook.detach().clone()
    assert vq(z).num_restarted == 0 and torch.equal(vq.codebook.detach(), before)  # no restarts at inference


@pytest.fixture(scope="module")
def trained_on_hidden_shifts():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    model = LAM(LAMConfig(**TINY))
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(300):
        past, nxt, _ = shifted_pairs(gen, 32)
        out = model(past, nxt)
        optimizer.zero_grad()
        out.loss.backward()
        optimizer.step()
    return model.eval(), gen


def test_lam_recovers_hidden_discrete_action(trained_on_hidden_shifts):
    model, gen = trained_on_hidden_shifts
    past, nxt, action = shifted_pairs(gen, 512)
    val_past, val_nxt, val_action = shifted_pairs(gen, 512)
    ids = model.infer_actions(past, nxt)
    val_ids = model.infer_actions(val_past, val_nxt)
    assert len(val_ids.unique()) >= 4  # codebook usage well beyond one code

    probe = action_probe(ids.numpy(), action.numpy(), val_ids.numpy(), val_action.numpy())
    assert probe["probe_acc"] > probe["majority_rate"] + 0.4, probe

    # A code that the probe maps to another action reconstructs the true next frame worse.
    mapping = probe["mapping"]
    wrong_ids = torch.tensor([next(c for c, label in mapping.items() if label != a) for a in val_action.tolist()])
    psnr_right = psnr(model.decode_with_actions(val_past, val_ids), val_nxt, (-1.0, 1.0)).mean()
    psnr_wrong = psnr(model.decode_with_actions(val_past, wrong_ids), val_nxt, (-1.0, 1.0)).mean()
    assert psnr_right > psnr_wrong + 2.0, (psnr_right, psnr_wrong)


def test_different_latent_actions_give_different_frames(trained_on_hidden_shifts):
    model, gen = trained_on_hidden_shifts
    past, _, _ = shifted_pairs(gen, 4)
    frames = [model.decode_with_actions(past, torch.full((4,), c)) for c in range(model.config.codebook_size)]
    smallest_change = min((frames[i] - frames[j]).abs().amax().item() for i in range(8) for j in range(i))
    assert smallest_change > 0.05


def test_save_load_round_trip(tmp_path, trained_on_hidden_shifts):
    model, gen = trained_on_hidden_shifts
    model.save_pretrained(tmp_path / "lam")
    assert sorted(p.name for p in (tmp_path / "lam").iterdir()) == ["MANIFEST.json", "config.json",
                                                                    "model.safetensors"]
    loaded = LAM.from_pretrained(tmp_path / "lam").eval()
    assert loaded.config == model.config
    past, nxt, _ = shifted_pairs(gen, 8)
    ids = model.infer_actions(past, nxt)
    assert torch.equal(loaded.infer_actions(past, nxt), ids)
    assert torch.allclose(loaded.decode_with_actions(past, ids), model.decode_with_actions(past, ids))
    # A loaded codebook is trained: further training must not re-initialise it.
    loaded.train()
    codebook = loaded.quantizer.codebook.detach().clone()
    assert loaded(past, nxt).num_restarted == 0 and torch.equal(loaded.quantizer.codebook.detach(), codebook)


def test_from_pretrained_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint directory not found"):
        LAM.from_pretrained(tmp_path / "nowhere")
    LAM(LAMConfig(**TINY)).save_pretrained(tmp_path / "a")
    (tmp_path / "a" / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        LAM.from_pretrained(tmp_path / "a")
    LAM(LAMConfig(**{**TINY, "channels": [8, 8]})).save_pretrained(tmp_path / "b")
    (tmp_path / "b" / "config.json").write_text(json.dumps(LAMConfig(**TINY).to_dict()))
    with pytest.raises(ValueError, match="does not match"):
        LAM.from_pretrained(tmp_path / "b")
    (tmp_path / "b" / "config.json").write_text(json.dumps({"codebook": 3}))
    with pytest.raises(ConfigError, match="config.json"):
        LAM.from_pretrained(tmp_path / "b")


def test_action_probe_hand_computed():
    # Train: code 0 -> label 5 (2 of 3), code 1 -> 7, code 2 -> 9; overall most frequent train label 7.
    result = action_probe([0, 0, 0, 1, 1, 2], [5, 5, 7, 7, 7, 9], [0, 1, 2, 3, 0], [5, 7, 7, 5, 7])
    # Predictions [5, 7, 9, 7 (unseen code -> 7), 5] vs [5, 7, 7, 5, 7]: 2 of 5 right.
    assert result["probe_acc"] == pytest.approx(0.4)
    assert result["majority_rate"] == pytest.approx(0.6)  # val's most frequent label 7: 3 of 5
    assert result["train_majority_rate"] == pytest.approx(0.6)
    assert result["mapping"] == {0: 5, 1: 7, 2: 9}
    with pytest.raises(ValueError, match="differ in length"):
        action_probe([0, 1], [1], [0], [1])


def test_transition_labels_and_valid_targets():
    buttons = np.array([[1, 0], [1, 0], [0, 1], [0, 1], [0, 1], [1, 1], [0, 0], [0, 0]], dtype=np.float32)
    assert button_combination_ids(buttons).tolist() == [1, 1, 2, 2, 2, 3, 0, 0]
    # Rows 0..2 -> {1, 1, 2}; rows 2..4 -> {2, 2, 2}; rows 4..6 -> {2, 3, 0}: a tie, the lowest id wins.
    assert transition_labels(buttons, np.array([3, 5, 7]), stride=3).tolist() == [1, 2, 0]
    assert combination_name(3, ["FORWARD", "LEFT"]) == "FORWARD+LEFT" and combination_name(0, ["A"]) == "NOOP"
    with pytest.raises(ValueError, match="targets must lie"):
        transition_labels(buttons, np.array([2]), stride=3)

    assert valid_targets(np.array([0, 0, 0, 0, 1, 1, 1, 1, 1]), gap=2).tolist() == [2, 3, 6, 7, 8]
    assert valid_targets(np.array([3, 3, 3, 1, 1, 1]), gap=2).tolist() == [2, 5]  # ids need not increase


def test_gather_transitions_order():
    frames = torch.arange(10, dtype=torch.uint8)[:, None, None, None].expand(10, 2, 2, 3).contiguous()
    past, nxt = gather_transitions(frames, np.array([6, 9]), stride=3, num_past_frames=2)
    to_index = lambda x: ((x[..., 0, 0, 0] + 1) * 127.5).round().long()
    assert to_index(past).tolist() == [[0, 3], [3, 6]]  # oldest first
    assert to_index(nxt).tolist() == [6, 9]


def write_sample_npz(path, segment_lengths, size=16, seed=0):
    """A sample-world-like .npz: a texture per segment rolled by TURN_LEFT / TURN_RIGHT buttons each frame."""
    rng = np.random.default_rng(seed)
    frames, segments, buttons = [], [], []
    for s, length in enumerate(segment_lengths):
        image = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        for _ in range(length):
            b = np.eye(3, dtype=np.float32)[rng.integers(0, 3)]  # NOOP-ish, TURN_LEFT, TURN_RIGHT
            frames.append(image)
            segments.append(s)
            buttons.append(b)
            image = np.roll(image, int(b[1]) - int(b[2]), axis=1)
    np.savez(path, frames=np.stack(frames), segment_ids=np.array(segments, dtype=np.int32),
             actions_buttons=np.stack(buttons), button_names=np.array(["USE", "TURN_LEFT", "TURN_RIGHT"]))


def test_train_lam_cli(tmp_path):
    write_sample_npz(tmp_path / "train.npz", [30, 30])
    write_sample_npz(tmp_path / "val.npz", [20], seed=1)
    out_dir = tmp_path / "lam"
    train_lam.main(["--train_data", str(tmp_path / "train.npz"), "--val_data", str(tmp_path / "val.npz"),
                    "--output_dir", str(out_dir), "--stride", "2", "--channels", "8,16", "--latent_dim", "8",
                    "--max_train_steps", "3", "--batch_size", "4", "--checkpointing_steps", "2", "--device", "cpu"])
    metrics = json.loads((out_dir / "metrics.json").read_text())
    assert metrics["delta_psnr"] == pytest.approx(metrics["psnr_inferred"] - metrics["psnr_random"])
    assert metrics["num_val_transitions"] == 18 and sum(metrics["code_histogram"]) == 18
    assert 0.0 <= metrics["action_majority_rate"] <= 1.0 and 0.0 <= metrics["action_probe_acc"] <= 1.0
    model = LAM.from_pretrained(out_dir)
    assert model.config.stride == 2 and model.config.channels == [8, 16]
    assert (out_dir / "checkpoint" / "model.safetensors").is_file()


def one_line_error(prog, main, argv, capsys) -> str:
    """The script's stderr when it stops on bad input: exit status 1, its last line "<prog>: error: ..."."""
    capsys.readouterr()
    assert run_main(prog, main, argv) == 1
    return capsys.readouterr().err.splitlines()[-1]


def test_train_lam_rejects_bad_data(tmp_path, capsys):
    np.savez(tmp_path / "bad.npz", frames=np.zeros((4, 16, 16, 3), dtype=np.float32), segment_ids=np.zeros(4))
    # one line naming the file, not a traceback
    line = one_line_error("lam.train", train_lam.main,
                          ["--train_data", str(tmp_path / "bad.npz"), "--val_data", str(tmp_path / "bad.npz")], capsys)
    assert re.match("^lam.train: error: .*bad.npz.*uint8", line)
    line = one_line_error("lam.train", train_lam.main, ["--train_data", str(tmp_path / "missing.npz")], capsys)
    assert re.match("^lam.train: error: frames file not found: .*missing.npz", line)
    np.savez(tmp_path / "no_segments.npz", frames=np.zeros((4, 16, 16, 3), dtype=np.uint8))
    line = one_line_error("lam.train", train_lam.main, ["--train_data", str(tmp_path / "no_segments.npz")], capsys)
    assert re.match(r"^lam.train: error: .*no_segments.npz: missing array\(s\) \['segment_ids'\]", line)
    with pytest.raises(SystemExit):
        train_lam.parse_args(["--channels", "16,x"])
    assert "argument --channels: expected comma-separated positive integers such as 16,32,64, got '16,x'" in \
        capsys.readouterr().err


def test_label_latent_actions_cli(tmp_path, capsys):
    lengths = [25, 12, 3]  # the last segment is shorter than the stride: no transition at all
    write_sample_npz(tmp_path / "frames.npz", lengths)
    n = sum(lengths)
    segment_ids = np.repeat(np.arange(len(lengths), dtype=np.int32), lengths)
    token_dir = tmp_path / "tokens"
    token_dir.mkdir()
    (token_dir / "metadata.json").write_text(json.dumps({"num_images": n, "s": 16, "vocab_size": 262144, "hz": 35}))
    segment_ids.tofile(token_dir / "segment_ids.bin")
    torch.manual_seed(0)
    model = LAM(LAMConfig(**{**TINY, "stride": 4})).eval()
    model.save_pretrained(tmp_path / "lam")

    label_latent_actions.main(["--lam_dir", str(tmp_path / "lam"), "--frames", str(tmp_path / "frames.npz"),
                               "--token_dir", str(token_dir), "--batch_size", "7", "--device", "cpu"])
    codes = np.fromfile(token_dir / "actions" / "latent_action.bin", dtype=np.float32).reshape(n, 1)[:, 0]
    targets = valid_targets(segment_ids, 4)
    frames = torch.from_numpy(np.load(tmp_path / "frames.npz")["frames"])
    expected = model.infer_actions(*gather_transitions(frames, targets, 4, 1)).numpy()
    assert np.array_equal(codes[targets], expected)
    assert np.all(codes[0:4] == codes[4]) and np.all(codes[25:29] == codes[29])  # first valid code of the segment
    most_frequent = np.bincount(expected, minlength=8).argmax()
    assert np.all(codes[37:] == most_frequent)
    sidecar = json.loads((token_dir / "actions" / "latent_action.json").read_text())
    assert sidecar["latent_action_stride"] == 4 and sidecar["latent_action_codebook_size"] == 8
    assert sidecar["num_inferred"] == len(targets) == n - 11
    assert sidecar["num_fallback_later_in_segment"] == 8 and sidecar["num_fallback_most_frequent"] == 3
    assert json.loads((token_dir / "metadata.json").read_text())["num_images"] == n  # left untouched

    (token_dir / "metadata.json").write_text(json.dumps({"num_images": n + 1}))
    line = one_line_error("lam.label", label_latent_actions.main,
                          ["--lam_dir", str(tmp_path / "lam"), "--frames", str(tmp_path / "frames.npz"),
                           "--token_dir", str(token_dir)], capsys)
    assert re.match("^lam.label: error: .*metadata.json: num_images", line)
    line = one_line_error("lam.label", label_latent_actions.main,
                          ["--lam_dir", str(tmp_path / "no_lam"), "--frames", str(tmp_path / "frames.npz"),
                           "--token_dir", str(token_dir)], capsys)
    assert re.match("^lam.label: error: LAM checkpoint directory not found: .*no_lam", line)
