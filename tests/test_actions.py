"""Action conditioning of the dynamics model: published layout kept, prompt-only rule, cache equivalence, and the
action paths of train.py, generate.py and evaluate.py (real actions and LAM latent actions)."""
import json

import numpy as np
import pytest
import torch

import evaluate
import train
import visualize
from data import RawTokenDataset, read_metadata, write_token_dataset
import evaluation.protocols
import generate as generate_script
from genie import GenieConfig, MaskGITBatch, STMaskGIT
from genie.inference import generate_frames, teacher_forced
from genie.reference import generate_uncached, teacher_forced_uncached
from lam.probe import button_combination_ids
from common.cli import run_main
from common.config import ConfigError

D, K = 3, 4  # real action width, latent action codebook size
SMALL = dict(num_layers=2, num_heads=2, d_model=32, T=5, S=16, image_vocab_size=64 ** 2, num_prompt_frames=2)


pytestmark = pytest.mark.usefixtures("one_thread")


def make_model(action_dim: int = D, num_latent_actions: int = K, seed: int = 0, **overrides) -> STMaskGIT:
    torch.manual_seed(seed)
    kwargs = dict(SMALL, num_latent_actions=num_latent_actions, **overrides)
    if action_dim:
        kwargs.update(action_names=["buttons"], action_dim=action_dim, action_mean=[0.5] * action_dim,
                      action_std=[2.0] * action_dim)
    model = STMaskGIT(GenieConfig(**kwargs))
    model.init_weights()
    with torch.no_grad():  # large weights, so that every input visibly changes the logits
        for module in model.modules():
            if isinstance(module, torch.nn.Linear):
                module.weight.normal_(0, module.in_features ** -0.5)
            if isinstance(module, torch.nn.Embedding):
                module.weight.normal_(0, 1.0)
        model.pos_embed_TSC.normal_(0, 1.0)
    return model.eval()


def random_inputs(model: STMaskGIT, B: int, T: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, model.config.image_vocab_size, (B, T, model.config.H, model.config.W), generator=g)
    actions = torch.randn(B, T, model.config.action_dim, generator=g) if model.config.action_dim else None
    latent = torch.randint(0, K, (B, T), generator=g) if model.config.num_latent_actions else None
    return x, actions, latent


def perturbed(actions, latent, start: int, seed: int):
    """Copies whose rows >= start hold other values."""
    g = torch.Generator().manual_seed(seed)
    actions2 = None if actions is None else actions.clone()
    latent2 = None if latent is None else latent.clone()
    if actions2 is not None:
        actions2[:, start:] = torch.randn(actions2[:, start:].shape, generator=g) * 3
    if latent2 is not None:
        latent2[:, start:] = (latent2[:, start:] + 1 + torch.randint(0, K - 1, latent2[:, start:].shape,
                                                                     generator=g)) % K
    return actions2, latent2


# ------------------------------------------------------------------ config and parameter layout
def published_keys(num_layers: int) -> set:
    """docs/formats.md §3's parameter names (qk_norm false)."""
    keys = {"pos_embed_TSC", "token_embed.mask_token_embed", "token_embed.factored_embeds.0.weight",
            "token_embed.factored_embeds.1.weight", "out_x_proj.weight", "out_x_proj.bias"}
    for i in range(num_layers):
        p = f"decoder.layers.{i}."
        keys |= {p + k for k in ("norm1.weight", "norm1.bias", "spatial_attn.qkv.weight", "spatial_attn.proj.weight",
                                 "spatial_attn.proj.bias", "temporal_attn.qkv.weight", "temporal_attn.proj.weight",
                                 "temporal_attn.proj.bias", "norm2.weight", "norm2.bias", "mlp.fc1.weight",
                                 "mlp.fc1.bias", "mlp.fc2.weight", "mlp.fc2.bias")}
    return keys


def test_default_config_keeps_the_published_layout():
    published_json = {"S": 16, "T": 4, "attn_drop": 0.0, "d_model": 32, "factored_vocab_size": 64,
                      "image_vocab_size": 4096, "max_corrupt_rate": 0.2, "mlp_bias": True, "mlp_drop": 0.0,
                      "mlp_ratio": 4.0, "non_mlm_ratio": 0.5, "num_factored_vocabs": 2, "num_heads": 2,
                      "num_layers": 2, "num_prompt_frames": 2, "proj_bias": True, "qk_norm": False,
                      "qkv_bias": False, "use_mup": False}
    config = GenieConfig.from_dict(published_json)
    assert not config.uses_actions
    model = STMaskGIT(config)
    assert set(model.state_dict()) == published_keys(2)
    assert model.action_cond is None

    with_actions = STMaskGIT(GenieConfig.from_dict({**published_json, "action_names": ["a", "b"], "action_dim": 3,
                                                    "num_latent_actions": 8}))
    added = {k: tuple(v.shape) for k, v in with_actions.state_dict().items() if k not in published_keys(2)}
    assert added == {"action_cond.action_proj.weight": (32, 3), "action_cond.action_proj.bias": (32,),
                     "action_cond.null_action_embed": (1, 32), "action_cond.latent_action_embed.weight": (9, 32)}


@pytest.mark.parametrize("fields, message", [
    ({"action_names": ["buttons"]}, "action_dim 0 must be > 0"),
    ({"action_dim": 2}, "must be > 0 exactly when"),
    ({"action_names": ["a", "a"], "action_dim": 2}, "distinct"),
    ({"action_names": ["a"], "action_dim": 2, "action_mean": [0.0, 0.0]}, "given together"),
    ({"action_names": ["a"], "action_dim": 2, "action_mean": [0.0], "action_std": [1.0]}, "need action_dim = 2"),
    ({"action_names": ["a"], "action_dim": 1, "action_mean": [0.0], "action_std": [0.0]}, "positive"),
    ({"num_latent_actions": -1}, "num_latent_actions"),
    ({"action_names": ["latent_action"], "action_dim": 1}, "use num_latent_actions"),
    ({"action_step_mean": True}, "action_step_mean needs real action streams"),
])
def test_bad_action_fields_are_config_errors(fields, message):
    with pytest.raises(ConfigError, match=message):
        GenieConfig(**SMALL, **fields)


def test_action_config_and_weights_round_trip(tmp_path):
    model = make_model()
    model.save_pretrained(tmp_path / "ckpt")
    saved = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    assert saved["action_mean"] == [0.5] * D and saved["action_std"] == [2.0] * D
    loaded = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    x, actions, latent = random_inputs(model, 2, 5)
    with torch.no_grad():
        torch.testing.assert_close(loaded.logits(x, actions, latent), model.logits(x, actions, latent))


# ------------------------------------------------------------------ the prompt-only rule
@pytest.mark.parametrize("use_cache", [True, False])
def test_teacher_forced_target_sees_only_earlier_action_rows(use_cache):
    model = make_model()
    run = teacher_forced if use_cache else teacher_forced_uncached
    x, actions, latent = random_inputs(model, 2, 5)
    _, logits = run(model, x, maskgit_steps=1, actions=actions, latent_actions=latent)
    for t in range(1, 5):
        later_actions, later_latent = perturbed(actions, latent, t, seed=t)
        _, logits2 = run(model, x, maskgit_steps=1, actions=later_actions, latent_actions=later_latent)
        torch.testing.assert_close(logits2[:, :, :, t - 1], logits[:, :, :, t - 1])  # rows >= t: no effect on t
        if t < 4:  # ... but they do change later targets
            assert not torch.allclose(logits2[:, :, :, t:], logits[:, :, :, t:], atol=1e-3)
    # the real action of frame t-1 drives target t
    prev_actions, _ = perturbed(actions, latent, 2, seed=9)
    prev_actions[:, 3:] = actions[:, 3:]
    _, logits3 = run(model, x, maskgit_steps=1, actions=prev_actions, latent_actions=latent)
    assert not torch.allclose(logits3[:, :, :, 2], logits[:, :, :, 2], atol=1e-3)  # target 3 uses row 2


def test_generation_ignores_actions_after_the_prompt_unless_controlled():
    model = make_model()
    x, actions, latent = random_inputs(model, 2, 5)
    P = 2
    later_actions, later_latent = perturbed(actions, latent, P, seed=1)

    def run(a, la, **kw):
        return generate_frames(model, x[:, :P], 3, maskgit_steps=2, temperature=1.0, actions=a, latent_actions=la,
                        generator=torch.Generator().manual_seed(5), **kw)

    tokens, logits = run(actions, latent)
    tokens2, logits2 = run(later_actions, later_latent)
    assert torch.equal(tokens, tokens2) and torch.equal(logits, logits2)
    _, controlled = run(actions, latent, control=True)
    _, controlled2 = run(later_actions, later_latent, control=True)
    assert not torch.allclose(controlled, controlled2, atol=1e-3)
    # NaN marks unknown real rows: controlled generation with NaN after the prompt equals the prompt-only rule
    # for the real actions (latent rows beyond the prompt are the "no action" id in both)
    nan_actions = actions.clone()
    nan_actions[:, P:] = float("nan")
    no_latent = latent.clone()
    no_latent[:, P:] = K
    _, nan_logits = run(nan_actions, no_latent, control=True)
    torch.testing.assert_close(nan_logits, logits)


# ------------------------------------------------------------------ cache == full recomputation
@pytest.mark.parametrize("action_dim, num_latent", [(D, 0), (0, K), (D, K)])
def test_cached_equals_uncached_with_actions(action_dim, num_latent):
    model = make_model(action_dim, num_latent, seed=1, qk_norm=True)
    x, actions, latent = random_inputs(model, 2, 5, seed=1)
    runs = [run(model, x, 2, 1.0, generator=torch.Generator().manual_seed(3), actions=actions,
                latent_actions=latent) for run in (teacher_forced, teacher_forced_uncached)]
    torch.testing.assert_close(runs[0][1], runs[1][1], atol=1e-5, rtol=1e-5)
    assert torch.equal(runs[0][0], runs[1][0])
    for control in (False, True):
        runs = [run(model, x[:, :2], 3, 2, 1.0, generator=torch.Generator().manual_seed(4), actions=actions,
                    latent_actions=latent, control=control) for run in (generate_frames, generate_uncached)]
        torch.testing.assert_close(runs[0][1], runs[1][1], atol=1e-5, rtol=1e-5)
        assert torch.equal(runs[0][0], runs[1][0])


def test_latent_action_changes_the_generated_frame():
    model = make_model(action_dim=0)
    x, _, latent = random_inputs(model, 1, 5)
    logits = []
    for action in (0, 3):
        played = latent.clone()
        played[:, 2:] = action
        logits.append(generate_frames(model, x[:, :2], 3, maskgit_steps=1, latent_actions=played, control=True)[1])
    assert not torch.allclose(logits[0][:, :, :, 0], logits[1][:, :, :, 0], atol=1e-3)


def test_training_forward_uses_actions_and_drops_them():
    x, actions, latent = random_inputs(make_model(), 2, 5)
    for dropout, expect_effect in ((0.0, True), (1.0, False)):
        model = make_model(action_dropout=dropout).train()
        with_actions = model.logits(x, actions=actions, latent_actions=latent)
        without = model.logits(x)
        assert torch.allclose(with_actions, without) != expect_effect
    model = make_model(action_dropout=0.0).train()
    masked = x.clone()
    masked[:, 1:] = model.mask_token_id  # the loss counts masked tokens only
    model(MaskGITBatch(masked, x, actions=actions, latent_actions=latent)).loss.backward()
    assert model.action_cond.action_proj.weight.grad.abs().sum() > 0
    assert model.action_cond.latent_action_embed.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="actions must be float"):
        model(MaskGITBatch(x, x, actions=actions[:, :, :2]))
    with pytest.raises(ValueError, match="latent action ids must be in"):
        model(MaskGITBatch(x, x, latent_actions=latent + K + 1))
    with pytest.raises(ValueError, match="no action inputs"):
        generate_frames(make_model(0, 0), x[:, :2], 1, actions=actions)


# ------------------------------------------------------------------ scripts
def make_action_dataset(path, num_segments: int, length: int, seed: int, s: int = 4, vocab: int = 4096):
    """Tokens, buttons (N, 2) 0/1, driving_command (N, 2), and latent ids = the button combination of the previous
    frame (latent_action.bin row f is the transition f-1 -> f), with the label_latent_actions.py sidecar."""
    rng = np.random.default_rng(seed)
    n = num_segments * length
    buttons = rng.integers(0, 2, size=(n, 2)).astype(np.float32)
    latent = np.concatenate([[0], button_combination_ids(buttons)[:-1]]).astype(np.float32)[:, None]
    actions = {"buttons": buttons, "driving_command": rng.normal(3.0, 2.0, size=(n, 2)).astype(np.float32),
               "latent_action": latent}
    write_token_dataset(path, rng.integers(0, vocab, size=(n, s, s)),
                        segment_ids=np.repeat(np.arange(num_segments), length), actions=actions,
                        metadata={"vocab_size": vocab, "hz": 10, "tokenizer_ckpt": "data/tiny_tokenizer"})
    (path / "actions" / "latent_action.json").write_text(json.dumps({"latent_action_stride": 1,
                                                                      "latent_action_num_past_frames": 1}))
    return path, actions


@pytest.fixture(scope="module")
def action_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("action_data")
    train_dir, train_actions = make_action_dataset(root / "train", 6, 12, seed=0)
    val_dir, _ = make_action_dataset(root / "val", 3, 16, seed=1)
    config = root / "tiny.json"
    config.write_text(json.dumps({"num_layers": 2, "num_heads": 2, "d_model": 32, "T": 4, "S": 16,
                                  "image_vocab_size": 4096, "num_prompt_frames": 2}))
    return {"root": root, "train": train_dir, "val": val_dir, "config": config, "train_actions": train_actions}


def test_train_with_actions_stores_normalization(action_data, tmp_path):
    out = tmp_path / "run"
    train.main(["--genie_config", str(action_data["config"]), "--train_data_dir", str(action_data["train"]),
                "--val_data_dir", str(action_data["val"]), "--output_dir", str(out), "--window_size", "4",
                "--stride", "1", "--per_device_train_batch_size", "4", "--max_train_steps", "2",
                "--eval_every_n_steps", "2", "--max_eval_steps", "1", "--checkpointing_steps", "0", "--no_compile",
                "--use_actions", "driving_command,buttons", "--use_latent_actions", str(K)])
    saved = json.loads((out / "final_checkpt" / "config.json").read_text())
    stacked = np.concatenate([action_data["train_actions"]["driving_command"],
                              action_data["train_actions"]["buttons"]], axis=1).astype(np.float64)
    assert saved["action_names"] == ["driving_command", "buttons"] and saved["action_dim"] == 4
    assert saved["num_latent_actions"] == K
    np.testing.assert_allclose(saved["action_mean"], stacked.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(saved["action_std"], stacked.std(axis=0), rtol=1e-4)
    model = STMaskGIT.from_pretrained(out / "final_checkpt")
    assert model.action_cond.action_proj.weight.shape == (32, 4)

    with pytest.raises(SystemExit, match="joint_pos.bin"):
        train.main(["--genie_config", str(action_data["config"]), "--train_data_dir", str(action_data["train"]),
                    "--val_data_dir", str(action_data["val"]), "--output_dir", str(tmp_path / "bad"),
                    "--window_size", "4", "--stride", "1", "--max_train_steps", "1", "--use_actions", "joint_pos"])


def step_means(values, num_segments, length, stride):
    """Row f: mean of rows f .. f + stride - 1 of f's segment (make_action_dataset's equal-length segments)."""
    out = np.empty_like(values, dtype=np.float64)
    for f in range(len(values)):
        end = min(f + stride, (f // length + 1) * length)
        out[f] = values[f:end].mean(axis=0)
    return out


def test_train_and_rollout_with_step_mean_actions(action_data, tmp_path, capsys, monkeypatch, stub_scorer):
    out = tmp_path / "run"
    argv = ["--genie_config", str(action_data["config"]), "--train_data_dir", str(action_data["train"]),
            "--val_data_dir", str(action_data["val"]), "--output_dir", str(out), "--window_size", "4",
            "--stride", "3", "--per_device_train_batch_size", "4", "--max_train_steps", "2",
            "--eval_every_n_steps", "2", "--max_eval_steps", "1", "--checkpointing_steps", "0", "--no_compile",
            "--use_actions", "driving_command"]
    train.main(argv + ["--action_step_mean"])
    saved = json.loads((out / "final_checkpt" / "config.json").read_text())
    assert saved["action_step_mean"] is True
    means = step_means(action_data["train_actions"]["driving_command"], 6, 12, 3)
    np.testing.assert_allclose(saved["action_mean"], means.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(saved["action_std"], means.std(axis=0), rtol=1e-4)
    assert not np.allclose(saved["action_std"], action_data["train_actions"]["driving_command"].std(axis=0),
                           rtol=1e-2)  # the means vary less than the rows

    calls = []

    def spy(model, prompt_BTHW, num_new_frames, *args, **kwargs):
        calls.append(kwargs)
        return generate_frames(model, prompt_BTHW, num_new_frames, *args, **kwargs)

    monkeypatch.setattr(evaluation.protocols, "generate_frames", spy)
    assert evaluate.main(["--val_data_dir", str(action_data["val"]), "--checkpoint_dir", str(out / "final_checkpt"),
                          "--window_size", "4", "--stride", "3", "--device", "cpu", "--max_examples", "3",
                          "--tokenizer_ckpt", "stub", "--skip_lpips", "--protocol", "rollout",
                          "--num_prompt_frames", "2"]) == 0
    val = RawTokenDataset(action_data["val"], window_size=4, stride=3, filter_overlaps=True)
    _, val_actions = make_action_dataset(tmp_path / "val_copy", 3, 16, seed=1)
    val_means = step_means(val_actions["driving_command"], 3, 16, 3)
    played = calls[0]["actions"].numpy()
    for i in range(3):  # the evaluator reads the step means the model was trained on
        np.testing.assert_allclose(played[i], val_means[int(val.valid_start_inds[i])::3][:4], rtol=1e-5)

    with pytest.raises(SystemExit, match="--action_step_mean.*--use_actions"):
        train.main(argv[:-2] + ["--output_dir", str(tmp_path / "bad"), "--action_step_mean"])


@pytest.fixture(scope="module")
def latent_ckpt(action_data):
    model = make_model(action_dim=0, T=4, S=16, image_vocab_size=4096)
    path = action_data["root"] / "latent_ckpt"
    model.save_pretrained(path)
    return path


def test_generate_plays_latent_actions_and_writes_them(action_data, latent_ckpt, tmp_path):
    def run(out, *extra):
        generate_script.main(["--val_data_dir", str(action_data["val"]), "--checkpoint_dir", str(latent_ckpt),
                       "--output_dir", str(out), "--window_size", "4", "--num_prompt_frames", "2", "--stride", "1",
                       "--num_examples", "3", "--device", "cpu", *extra])
        meta = read_metadata(out)
        video = np.fromfile(out / "video.bin", dtype=meta["token_dtype"]).reshape(3, 6, 4, 4)
        ids = np.fromfile(out / "actions" / "latent_action.bin", dtype=np.float32).reshape(3, 6)
        return meta, video, ids

    meta, video, ids = run(tmp_path / "a", "--latent_actions", "1,3")
    assert meta["latent_actions"] == [1, 3]
    np.testing.assert_array_equal(ids[:, 2:4], [[1, 3]] * 3)  # the played ids label the generated frames
    val = RawTokenDataset(action_data["val"], window_size=4, stride=1)
    data_ids = np.stack([val.get_window_actions(int(val.valid_start_inds[i]))["latent_action"][:, 0]
                         for i in range(3)])
    np.testing.assert_array_equal(ids[:, 1], data_ids[:, 1])  # prompt frame 1: the data's id
    np.testing.assert_array_equal(ids[:, 4:], data_ids[:, 2:])  # ground truth frames
    assert (ids[:, 0] == -1).all()  # frame 0 is never conditioned
    label = visualize.action_labels(RawTokenDataset(tmp_path / "a", window_size=1, filter_interrupts=False),
                                    "latent_action")
    assert label(2) == "latent_action 1" and label(3) == "latent_action 3"

    _, other_video, _ = run(tmp_path / "b", "--latent_actions", "2")
    assert not np.array_equal(video[:, 2:4], other_video[:, 2:4])  # the played actions change the frames
    np.testing.assert_array_equal(video[:, :2], other_video[:, :2])

    with pytest.raises(ValueError, match="outside"):
        run(tmp_path / "c", "--latent_actions", f"{K},0")


@pytest.fixture
def stub_scorer(monkeypatch):
    class StubScorer:
        """Decodes token t to a flat 4x4 patch of value t % 256 (16x16 images: SSIM needs 11x11)."""

        def __init__(self, tokenizer_ckpt, device, with_lpips=True):
            pass

        def decode(self, tokens_NHW):
            images_NHW = (tokens_NHW % 256).to(torch.uint8).repeat_interleave(4, 1).repeat_interleave(4, 2)
            return images_NHW[:, :, :, None].expand(-1, -1, -1, 3)

        def lpips_distances(self, images_a, images_b):
            return (images_a.float() - images_b.float()).abs().mean(dim=(1, 2, 3)) / 255

    monkeypatch.setattr(evaluation.protocols, "FrameScorer", StubScorer)


def test_evaluate_adds_latent_action_metrics(action_data, latent_ckpt, tmp_path, capsys, stub_scorer):
    argv = ["--val_data_dir", str(action_data["val"]), "--train_data_dir", str(action_data["train"]),
            "--window_size", "4", "--stride", "1", "--batch_size", "4", "--device", "cpu", "--max_examples", "6",
            "--tokenizer_ckpt", "stub"]
    assert evaluate.main(argv + ["--checkpoint_dir", str(latent_ckpt)]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"delta_psnr", "action_probe_acc", "action_majority_rate"} <= set(result)
    assert result["delta_psnr"] != 0.0
    # latent ids are the previous frame's button combination, so the probe is exact; buttons are random
    assert result["action_probe_acc"] == 1.0 and result["action_majority_rate"] < 0.5

    # without any effect of the latent actions both generations are identical: delta_psnr is exactly 0
    model = STMaskGIT.from_pretrained(latent_ckpt)
    with torch.no_grad():
        model.action_cond.latent_action_embed.weight.zero_()
    model.save_pretrained(tmp_path / "inert")
    assert evaluate.main(argv + ["--checkpoint_dir", str(tmp_path / "inert")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["delta_psnr"] == 0.0


def test_delta_psnr_seeds_average_the_single_seed_runs(action_data, latent_ckpt, capsys, stub_scorer):
    argv = ["--val_data_dir", str(action_data["val"]), "--window_size", "4", "--stride", "1", "--batch_size", "4",
            "--device", "cpu", "--max_examples", "6", "--tokenizer_ckpt", "stub", "--temperature", "1",
            "--checkpoint_dir", str(latent_ckpt), "--train_data_dir", str(action_data["train"])]

    def result(*extra):
        assert evaluate.main(argv + list(extra)) == 0
        return json.loads(capsys.readouterr().out.strip().splitlines()[-1])

    single = [result("--seed", str(seed))["delta_psnr"] for seed in (3, 4, 5)]
    assert len(set(single)) > 1  # the sampler's seed matters, so the repeats differ
    repeated = result("--seed", "3", "--delta_psnr_seeds", "3")
    assert repeated["delta_psnr_runs"] == pytest.approx(single, abs=1e-9)
    assert repeated["delta_psnr"] == pytest.approx(sum(single) / 3, abs=1e-9)
    assert result("--seed", "3")["delta_psnr_runs"] == pytest.approx(single[:1], abs=1e-9)
    with pytest.raises(SystemExit):
        evaluate.main(argv + ["--delta_psnr_seeds", "0"])


def test_rollout_plays_the_windows_action_rows(action_data, latent_ckpt, capsys, monkeypatch, stub_scorer):
    calls = []

    def spy(model, prompt_BTHW, num_new_frames, *args, **kwargs):
        calls.append((prompt_BTHW.shape[1], num_new_frames, kwargs))
        return generate_frames(model, prompt_BTHW, num_new_frames, *args, **kwargs)

    monkeypatch.setattr(evaluation.protocols, "generate_frames", spy)
    argv = ["--val_data_dir", str(action_data["val"]), "--checkpoint_dir", str(latent_ckpt), "--window_size", "4",
            "--stride", "1", "--batch_size", "4", "--device", "cpu", "--max_examples", "4", "--tokenizer_ckpt",
            "stub", "--skip_lpips", "--protocol", "rollout", "--num_prompt_frames", "1"]
    assert evaluate.main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["num_examples"] == 4 and len(result["rollout_psnr"]) == 3
    assert "delta_psnr" not in result  # the rollout protocol reports its own keys only
    (prompt_frames, new_frames, kwargs), = calls
    assert (prompt_frames, new_frames, kwargs["control"]) == (1, 3, True)
    val = RawTokenDataset(action_data["val"], window_size=4, stride=1, filter_overlaps=True)
    rows = np.stack([val[i]["actions"]["latent_action"][:, 0] for i in range(4)])
    np.testing.assert_array_equal(kwargs["latent_actions"].numpy(), rows)  # every row of the window is played


def test_evaluate_needs_the_checkpoints_action_streams(latent_ckpt, tmp_path, capsys):
    write_token_dataset(tmp_path / "plain", np.zeros((20, 4, 4), dtype=np.int64), metadata={"vocab_size": 4096})
    argv = ["--val_data_dir", str(tmp_path / "plain"), "--checkpoint_dir", str(latent_ckpt), "--window_size", "4",
            "--stride", "1", "--device", "cpu", "--skip_lpips"]
    assert run_main("evaluate.py", evaluate.main, argv) == 1
    assert "latent_action.bin" in capsys.readouterr().err


