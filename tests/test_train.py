"""train.py on CPU with a tiny model: learning, checkpoints (round trip, in-process resume), data order, errors."""
import json
import math

import numpy as np
import pytest
import torch
from accelerate.state import AcceleratorState
from safetensors.torch import load_file

import train
from common.schedules import LR_SCHEDULES, lr_multiplier
from data import RawTokenDataset, write_token_dataset
from genie import GenieConfig, STMaskGIT
from training.masking import get_maskgit_collator
from genie.reference import full_logits_loss
from common.ema import WeightAverage
from common.train_state import (COMPLETE_MARKER, EMA_DIR, ResumableBatchSampler, list_checkpoints,
                               load_training_checkpoint)

TINY = {"num_layers": 2, "num_heads": 2, "d_model": 32, "T": 4, "S": 16, "image_vocab_size": 4096,
        "num_prompt_frames": 2}


def make_token_dataset(path, segment_lengths, s=4, vocab_size=4096, num_distinct=8, seed=0):
    """A learnable dataset: each clip repeats one frame of tokens drawn from the same `num_distinct` ids (the
    ids do not depend on `seed`, the frames do)."""
    ids = np.random.default_rng(1234).choice(vocab_size, size=num_distinct, replace=False)
    rng = np.random.default_rng(seed)
    clips = [np.repeat(rng.choice(ids, size=(1, s, s)), n, axis=0) for n in segment_lengths]
    segment_ids = np.repeat(np.arange(len(segment_lengths)), segment_lengths)
    write_token_dataset(path, np.concatenate(clips), segment_ids=segment_ids,
                        metadata={"vocab_size": vocab_size, "hz": 10, "tokenizer_ckpt": "data/tiny_tokenizer"})
    return path


def write_config(path, **overrides):
    path.write_text(json.dumps({**TINY, **overrides}))
    return path


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_data")
    return {"train": make_token_dataset(root / "train", [8] * 12, seed=0),
            "val": make_token_dataset(root / "val", [8] * 3, seed=1),
            "config": write_config(root / "tiny.json")}


def train_argv(data, output_dir, *extra):
    return ["--genie_config", str(data["config"]), "--train_data_dir", str(data["train"]),
            "--val_data_dir", str(data["val"]), "--output_dir", str(output_dir), "--window_size", "4",
            "--stride", "1", "--per_device_train_batch_size", "4", "--per_device_eval_batch_size", "4",
            "--learning_rate", "3e-3", "--lr_scheduler_type", "constant", "--max_eval_steps", "2",
            "--eval_every_n_steps", "0", "--seed", "3", *extra]


def masked_val_loss(model, data_dir, config, num_windows=8):
    """The model's training loss on fixed, seeded masks of the first validation windows."""
    ds = RawTokenDataset(data_dir, window_size=config.T, stride=1)
    batch = get_maskgit_collator(config, seed=0)([ds[i] for i in range(num_windows)])
    with torch.no_grad():
        return full_logits_loss(model.eval(), batch).loss.item()


def load_weights(ckpt_dir):
    return load_file(str(ckpt_dir / "model.safetensors"))


def assert_same_weights(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def assert_close_weights(actual, expected, **tolerance):
    assert actual.keys() == expected.keys()
    for k in expected:
        torch.testing.assert_close(actual[k], expected[k], **tolerance)


def test_training_lowers_the_loss(tiny_data, tmp_path):
    train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "30", "--checkpointing_steps", "0"))
    config = GenieConfig.from_pretrained(tiny_data["config"])
    torch.manual_seed(0)
    untrained = STMaskGIT(config)
    untrained.init_weights()
    trained = STMaskGIT.from_pretrained(tmp_path / "final_checkpt")
    before = masked_val_loss(untrained, tiny_data["val"], config)
    after = masked_val_loss(trained, tiny_data["val"], config)
    assert after < 0.7 * before, (before, after)
    assert not list_checkpoints(tmp_path)  # --checkpointing_steps 0 writes only final_checkpt


def test_gradient_checkpointing_trains_the_same_weights(tiny_data, tmp_path):
    """--gradient_checkpointing recomputes activations in the backward pass: the same run, the same weights."""
    steps = ("--max_train_steps", "3", "--checkpointing_steps", "0")
    train.main(train_argv(tiny_data, tmp_path / "plain", *steps))
    train.main(train_argv(tiny_data, tmp_path / "recomputed", *steps, "--gradient_checkpointing"))
    plain, recomputed = (load_weights(tmp_path / run / "final_checkpt") for run in ("plain", "recomputed"))
    assert_close_weights(recomputed, plain, atol=1e-6, rtol=1e-5)


def test_checkpoint_round_trip_and_in_process_resume(tiny_data, tmp_path):
    full, resumed = tmp_path / "full", tmp_path / "resumed"
    extra = ("--max_train_steps", "6", "--checkpointing_steps", "2", "--checkpoints_total_limit", "0",
             "--gradient_accumulation_steps", "2", "--eval_every_n_steps", "3")
    train.main(train_argv(tiny_data, full, *extra))
    assert [step for step, _ in list_checkpoints(full)] == [2, 4, 6]

    ckpt = load_training_checkpoint(full / "checkpoint-6")
    assert ckpt["trainer"]["step"] == 6
    assert len(ckpt["rng"]) == 1 and ckpt["optimizer"]["state"]
    assert_same_weights(load_weights(full / "checkpoint-6"), load_weights(full / "final_checkpt"))
    reloaded = STMaskGIT.from_pretrained(full / "checkpoint-6")  # every checkpoint is also a HF model dir
    assert_same_weights({k: v for k, v in reloaded.state_dict().items()}, load_weights(full / "final_checkpt"))

    train.main(train_argv(tiny_data, resumed, *extra, "--resume_from_checkpoint", str(full / "checkpoint-2")))
    assert_same_weights(load_weights(full / "final_checkpt"), load_weights(resumed / "final_checkpt"))
    ckpt_resumed = load_training_checkpoint(resumed / "checkpoint-6")
    for group_a, group_b in zip(ckpt["optimizer"]["state"].values(), ckpt_resumed["optimizer"]["state"].values()):
        assert all(torch.equal(group_a[k], group_b[k]) for k in group_a)


def test_checkpoints_total_limit_and_latest(tiny_data, tmp_path):
    train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "3", "--checkpointing_steps", "1",
                          "--checkpoints_total_limit", "2"))
    assert [step for step, _ in list_checkpoints(tmp_path)] == [2, 3]
    # A later, half-written checkpoint (no marker) is ignored by "latest": the run resumes from step 3.
    (tmp_path / "checkpoint-9").mkdir()
    train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "4", "--checkpointing_steps", "1",
                          "--checkpoints_total_limit", "2", "--resume_from_checkpoint", "latest"))
    assert [step for step, _ in list_checkpoints(tmp_path)] == [3, 4]
    assert load_training_checkpoint(tmp_path / "checkpoint-4")["trainer"]["step"] == 4
    with pytest.raises(SystemExit, match="incomplete"):
        train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "10",
                              "--resume_from_checkpoint", str(tmp_path / "checkpoint-9")))


@pytest.mark.parametrize("override,data_key,pattern", [
    ({"T": 8, "num_prompt_frames": 2}, None, "window_size 4 must equal .* T=8"),
    ({"S": 64}, None, "4x4 = 16 tokens .* S=64"),
    ({"image_vocab_size": 1024}, None, "vocab_size 4096 differs .* 1024"),
    ({"two_stream_ratio": 0.5}, None, "two_stream_ratio was a dropped experiment and has been removed"),
])
def test_data_config_mismatch_is_a_clear_error(tiny_data, tmp_path, override, data_key, pattern):
    config = write_config(tmp_path / "bad.json", **override)
    data = {**tiny_data, "config": config}
    with pytest.raises(SystemExit, match=pattern):
        train.main(train_argv(data, tmp_path / "out", "--max_train_steps", "1"))


def test_val_data_mismatch_names_the_file(tiny_data, tmp_path):
    make_token_dataset(tmp_path / "val_s8", [12], s=8)
    data = {**tiny_data, "val": tmp_path / "val_s8"}
    with pytest.raises(SystemExit, match=r"val_s8/metadata.json: frames are 8x8"):
        train.main(train_argv(data, tmp_path / "out", "--max_train_steps", "1"))


def test_too_little_data_for_one_step(tiny_data, tmp_path):
    with pytest.raises(SystemExit, match="too few for one optimizer step"):
        train.main(train_argv(tiny_data, tmp_path, "--per_device_train_batch_size", "64", "--max_train_steps", "1"))


def test_sampler_order_depends_only_on_seed_and_epoch_and_shards_disjointly():
    def epoch(num_replicas, rank, e, seed=7, start=0):
        sampler = ResumableBatchSampler(50, 3, num_replicas, rank, seed=seed)
        sampler.set_epoch(e, start)
        return list(sampler)

    assert epoch(1, 0, 0) == epoch(1, 0, 0)
    assert epoch(1, 0, 0) != epoch(1, 0, 1) and epoch(1, 0, 0) != epoch(1, 0, 0, seed=8)
    assert epoch(1, 0, 2, start=5) == epoch(1, 0, 2)[5:]  # resuming skips exactly the batches already seen
    shards = [sum(epoch(2, r, 0), []) for r in range(2)]
    assert len(shards[0]) == len(shards[1]) == 24  # 25 windows per process -> 8 full batches of 3
    assert not set(shards[0]) & set(shards[1])
    assert all(len(b) == 3 for b in epoch(2, 1, 0))


def test_lr_schedules():
    linear = lr_multiplier("linear", warmup=2, total=10)
    assert [linear(s) for s in (0, 1, 2, 6, 10)] == pytest.approx([0, 0.5, 1, 0.5, 0])
    cosine = lr_multiplier("cosine", warmup=0, total=10)
    assert cosine(0) == pytest.approx(1) and cosine(5) == pytest.approx(0.5) and cosine(10) == pytest.approx(0)
    custom = lr_multiplier("custom_cosine", warmup=2, total=12)
    assert custom(0) == pytest.approx(0.5) and custom(12) == pytest.approx(0.1)
    assert lr_multiplier("constant", 5, 10)(0) == 1.0
    assert set(LR_SCHEDULES) == set(train.LR_SCHEDULES)
    with pytest.raises(ValueError, match="unknown learning-rate schedule"):
        lr_multiplier("step", 0, 10)


def test_lam_schedule_is_the_custom_cosine():
    """lam/train.py's schedule, before it used common.schedules: warmup to 1, then cosine to 10 %."""
    def lam_before(warmup_steps, total_steps):
        def f(step):
            if step < warmup_steps:
                return (step + 1) / warmup_steps
            progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
            return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))
        return f
    for warmup, total in ((50, 1200), (0, 10), (3, 3)):
        ours, before = lr_multiplier("custom_cosine", warmup, total), lam_before(warmup, total)
        assert [ours(s) for s in range(total + 2)] == [before(s) for s in range(total + 2)]


def test_help_hides_the_test_hooks(capsys):
    with pytest.raises(SystemExit):
        train.parse_args(["--help"])
    assert "debug" not in capsys.readouterr().out.lower()
    args = train.parse_args(["--debug_step_sleep", "0.5", "--debug_inject_nan_at_steps", "2", "3"])
    assert args.debug_step_sleep == 0.5 and args.debug_inject_nan_at_steps == [2, 3]


def test_checkpoint_layout_and_no_temp_leftovers(tiny_data, tmp_path):
    train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "1", "--checkpointing_steps", "1"))
    ckpt = tmp_path / "checkpoint-1"
    names = {p.name for p in ckpt.iterdir()}
    assert {COMPLETE_MARKER, "config.json", "model.safetensors", "optimizer.safetensors", "optimizer.json",
            "rng.safetensors", "rng.json", "trainer_state.json"} <= names
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]


def test_warmstart_loads_weights_and_rejects_other_shapes(tiny_data, tmp_path):
    torch.manual_seed(1)
    source = STMaskGIT(GenieConfig(**TINY))
    source.init_weights()
    source.save_pretrained(tmp_path / "source")
    train.main(train_argv(tiny_data, tmp_path / "run", "--max_train_steps", "0",
                          "--warmstart_path", str(tmp_path / "source")))
    assert_same_weights(load_weights(tmp_path / "source"), load_weights(tmp_path / "run" / "final_checkpt"))

    # a copy head (or action inputs) the source lacks starts fresh on top of the source's weights
    copy_config = write_config(tmp_path / "copy.json", copy_radius=1, copy_match_input=True)
    train.main(train_argv({**tiny_data, "config": copy_config}, tmp_path / "copy_run", "--max_train_steps", "0",
                          "--warmstart_path", str(tmp_path / "source")))
    copy_weights = load_weights(tmp_path / "copy_run" / "final_checkpt")
    assert {k for k in copy_weights if k.startswith("copy_head.")} == {
        "copy_head.score_proj.weight", "copy_head.score_proj.bias", "copy_head.match_proj.weight"}
    assert_same_weights(load_weights(tmp_path / "source"),
                        {k: v for k, v in copy_weights.items() if not k.startswith("copy_head.")})

    wide = STMaskGIT(GenieConfig(**{**TINY, "d_model": 64}))
    wide.save_pretrained(tmp_path / "wide")
    with pytest.raises(SystemExit, match=r"--warmstart_path .*wide.*shape mismatches"):
        train.main(train_argv(tiny_data, tmp_path / "run2", "--max_train_steps", "1",
                              "--warmstart_path", str(tmp_path / "wide")))


def test_missing_tracker_package_is_reported(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setattr(train.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(SystemExit, match="--report_to wandb needs the wandb package"):
        train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "1", "--report_to", "wandb"))


@pytest.fixture
def fresh_accelerate_state():
    """accelerate keeps one mixed-precision setting per process: a run in bf16 needs it cleared before and after."""
    AcceleratorState._reset_state(reset_partial_state=True)
    yield
    AcceleratorState._reset_state(reset_partial_state=True)


@pytest.mark.skipif(torch.cuda.is_available(), reason="the warning is about training on a CPU")
@pytest.mark.parametrize("native, warned", [(False, True), (True, False), (None, False)])
@pytest.mark.usefixtures("fresh_accelerate_state")
def test_cpu_bf16_without_native_support_warns(tiny_data, tmp_path, monkeypatch, caplog, native, warned):
    monkeypatch.setattr(train, "cpu_has_native_bf16", lambda: native)
    with caplog.at_level("WARNING", logger="train"):
        train.main(train_argv(tiny_data, tmp_path, "--max_train_steps", "0", "--mixed_precision", "bf16"))
    assert ("emulated" in caplog.text) is warned


def test_weight_average_follows_its_ramped_decay():
    """common/ema.py: a_n = d_n a_(n-1) + (1 - d_n) w_n with d_n = min(decay, (1 + n) / (10 + n)), buffers copied."""
    model = torch.nn.Linear(3, 2)
    model.register_buffer("scale", torch.tensor([2.0]))
    average = WeightAverage(model, decay=0.5)
    expected = {name: p.detach().clone() for name, p in model.named_parameters()}
    with torch.no_grad():
        for n, value in enumerate((1.0, -2.0, 4.0), start=1):
            assert average.current_decay() == min(0.5, (1 + n) / (10 + n))
            for p in model.parameters():
                p.fill_(value)
            d = average.current_decay()
            expected = {name: d * a + (1 - d) * value for name, a in expected.items()}
            average.update(model)
    assert average.updates == 3
    for name, p in average.model.named_parameters():
        torch.testing.assert_close(p, expected[name], rtol=0, atol=1e-6)
        assert not p.requires_grad
    assert torch.equal(average.model.scale, model.scale)
    assert not any(p.data_ptr() == q.data_ptr() for p, q in zip(average.model.parameters(), model.parameters()))
    with pytest.raises(ValueError, match="decay must be in"):
        WeightAverage(model, decay=1.0)


def test_ema_decay_writes_the_average_and_resumes_it_exactly(tiny_data, tmp_path):
    full, resumed, plain = tmp_path / "full", tmp_path / "resumed", tmp_path / "plain"
    extra = ("--max_train_steps", "6", "--checkpointing_steps", "2", "--checkpoints_total_limit", "0",
             "--eval_every_n_steps", "3")
    train.main(train_argv(tiny_data, full, *extra, "--ema_decay", "0.9"))
    train.main(train_argv(tiny_data, plain, *extra))
    final, raw = load_weights(full / "final_checkpt"), load_weights(full / "checkpoint-6")
    assert_same_weights(final, load_weights(full / "checkpoint-6" / EMA_DIR))
    assert_same_weights(raw, load_weights(plain / "final_checkpt"))  # the average leaves training alone
    assert any(not torch.equal(final[k], raw[k]) for k in raw)
    assert load_training_checkpoint(full / "checkpoint-6")["trainer"]["ema_updates"] == 6
    assert not (plain / "checkpoint-6" / EMA_DIR).exists()
    STMaskGIT.from_pretrained(full / "final_checkpt")

    train.main(train_argv(tiny_data, resumed, *extra, "--ema_decay", "0.9",
                          "--resume_from_checkpoint", str(full / "checkpoint-2")))
    assert_same_weights(final, load_weights(resumed / "final_checkpt"))


def test_ema_decay_from_a_checkpoint_without_an_average_starts_one(tiny_data, tmp_path, caplog):
    train.main(train_argv(tiny_data, tmp_path / "plain", "--max_train_steps", "2", "--checkpointing_steps", "2"))
    with caplog.at_level("WARNING", logger="train"):
        train.main(train_argv(tiny_data, tmp_path / "averaged", "--max_train_steps", "4", "--ema_decay", "0.5",
                              "--resume_from_checkpoint", str(tmp_path / "plain" / "checkpoint-2")))
    assert "holds no weight average" in caplog.text
    assert load_training_checkpoint(tmp_path / "averaged" / "checkpoint-4")["trainer"]["ema_updates"] == 2


@pytest.mark.parametrize("value", ["1", "-0.1", "nan"])
def test_ema_decay_out_of_range_is_a_usage_error(value, capsys):
    with pytest.raises(SystemExit):
        train.parse_args(["--ema_decay", value])
    assert "--ema_decay" in capsys.readouterr().err
