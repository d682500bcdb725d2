"""Run recipes (training/recipe.py, recipes/*.json): train.py --recipe, the resolved recipe every checkpoint keeps
(recipe.json, decoding.json), the errors of a bad recipe, and the shipped recipes themselves."""
import json
import os
import re
import subprocess
from pathlib import Path

import pytest

import train
from genie import GenieConfig, STMaskGIT
from genie.decoding import DecodingConfig
from training.recipe import load_model_config, load_recipe
from tests.test_train import TINY, assert_same_weights, load_weights, make_token_dataset, train_argv, write_config

REPO = Path(__file__).resolve().parents[1]
RECIPES = REPO / "recipes"
CONFIG_DIR = REPO / "genie" / "configs"
DECODING = {"maskgit_steps": 3, "temperature": 1.0, "copy_bias": 2.0, "greedy_tokens": "best_neighbour"}
# train_argv's flags (tests/test_train.py)
TRAIN = {"window_size": 4, "stride": 1, "per_device_train_batch_size": 4, "per_device_eval_batch_size": 4,
         "learning_rate": 3e-3, "lr_scheduler_type": "constant", "max_eval_steps": 2, "eval_every_n_steps": 0,
         "seed": 3, "max_train_steps": 2, "checkpointing_steps": 2}

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("recipe_data")
    return {"train": make_token_dataset(root / "train", [8] * 12, seed=0),
            "val": make_token_dataset(root / "val", [8] * 3, seed=1),
            "config": write_config(root / "tiny.json", copy_radius=1, copy_match_input=True)}


def write_recipe(path: Path, model=None, train_values=None, decoding=None, **sections) -> Path:
    recipe = {"model": {**TINY, "copy_radius": 1, "copy_match_input": True} if model is None else model,
              "train": TRAIN if train_values is None else train_values,
              "decoding": DECODING if decoding is None else decoding, **sections}
    path.write_text(json.dumps(recipe))
    return path


def recipe_argv(data, recipe: Path, output_dir: Path, *extra) -> list:
    return ["--recipe", str(recipe), "--train_data_dir", str(data["train"]), "--val_data_dir", str(data["val"]),
            "--output_dir", str(output_dir), *extra]


# ---------------------------------------------------------------- flags

def test_the_recipe_sets_the_defaults_and_a_flag_overrides_one(tmp_path):
    recipe = write_recipe(tmp_path / "r.json", train_values={**TRAIN, "gradient_checkpointing": True})
    args = train.parse_args(["--recipe", str(recipe)])
    assert (args.learning_rate, args.lr_scheduler_type, args.max_train_steps) == (3e-3, "constant", 2)
    assert args.checkpointing_steps == "2" and args.gradient_checkpointing  # converted as the flag's own value
    args = train.parse_args(["--recipe", str(recipe), "--learning_rate", "0.5"])
    assert args.learning_rate == 0.5 and args.max_train_steps == 2  # only the flag given changes
    plain = train.parse_args([])  # without a recipe: the old defaults
    assert (plain.learning_rate, plain.max_train_steps, plain.checkpointing_steps) == (1e-4, None, "1000")


def test_the_shipped_recipes_are_the_shell_jobs_old_flags():
    """recipes/sample_world.json trains what run_sample.sh's flags trained; recipes/gpu_world.json what run_gpu.sh's
    flags made of them; COMPILE=1's --compile turns the GPU recipe's no_compile off."""
    sample = vars(train.parse_args(["--recipe", str(RECIPES / "sample_world.json")]))
    flags = vars(train.parse_args(
        ["--per_device_train_batch_size", "2", "--optimizer", "muon", "--learning_rate", "1e-2",
         "--lr_scheduler_type", "linear", "--num_warmup_steps", "120", "--max_train_steps", "1600",
         "--weight_decay", "0.4", "--eval_every_n_steps", "800", "--max_eval_steps", "16",
         "--checkpointing_steps", "800"]))
    assert {k: v for k, v in sample.items() if k != "recipe"} == {k: v for k, v in flags.items() if k != "recipe"}
    gpu = vars(train.parse_args(["--recipe", str(RECIPES / "gpu_world.json")]))
    changed = {k: v for k, v in gpu.items() if sample[k] != v}
    assert changed == {"recipe": str(RECIPES / "gpu_world.json"), "per_device_train_batch_size": 32,
                       "max_train_steps": 900, "num_warmup_steps": 45, "learning_rate": 3e-3, "no_compile": True,
                       "eval_every_n_steps": 300, "max_eval_steps": 32, "checkpointing_steps": "300"}
    assert not train.parse_args(["--recipe", str(RECIPES / "gpu_world.json"), "--compile"]).no_compile
    for name in ("sample_world", "gpu_world"):
        assert load_recipe(RECIPES / f"{name}.json").decoding == DecodingConfig(
            maskgit_steps=2, temperature=1.0, copy_bias=2.0, greedy_tokens="best_neighbour")


@pytest.mark.parametrize("recipe, message", [
    ({"model": TINY, "trian": {}}, r"unknown section\(s\) \['trian'\]"),
    ({"model": {**TINY, "num_layer": 2}}, r"unknown key\(s\) \['num_layer'\]"),
    ({"model": TINY, "train": {"learning_rat": 0.1}}, r"unknown train.py flag 'learning_rat' in \"train\""),
    ({"model": TINY, "train": {"debug_step_sleep": 1}}, r"unknown train.py flag 'debug_step_sleep'"),
    ({"model": TINY, "decoding": {"copy_bais": 1.0}}, r"decoding: unknown key\(s\) \['copy_bais'\]"),
    ({"model": TINY, "decoding": {"maskgit_steps": 0}}, r"decoding: maskgit_steps must be >= 1"),
    ({"model": TINY, "train": {"max_train_steps": 2.5}}, r"train.max_train_steps: 2.5 is not a value"),
    ({"model": TINY, "train": {"optimizer": "sgd"}}, r"train.optimizer: must be one of \['adamw', 'muon'\]"),
    ({"model": TINY, "train": {"no_compile": 1}}, r"train.no_compile: must be true or false"),
    ({"train": {}}, r"needs a \"model\" section"),
    ([TINY], r"a run recipe is a JSON object"),
])
def test_a_bad_recipe_is_a_one_line_error_naming_the_file(tmp_path, capsys, recipe, message):
    path = tmp_path / "bad_recipe.json"
    path.write_text(json.dumps(recipe))
    with pytest.raises(SystemExit) as stop:
        train.parse_args(["--recipe", str(path)])
    assert stop.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"error: {path}: " in error, error  # one line, naming the file
    assert re.search(message, error), error


def test_a_missing_recipe_file_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        train.parse_args(["--recipe", str(tmp_path / "nowhere.json")])
    assert f"error: run recipe file not found: {tmp_path / 'nowhere.json'}" in capsys.readouterr().err


def test_genie_config_reads_a_recipe_s_model(tmp_path):
    recipe = write_recipe(tmp_path / "r.json")
    assert load_model_config(recipe) == load_model_config(write_config(tmp_path / "c.json", copy_radius=1,
                                                                       copy_match_input=True))


# ---------------------------------------------------------------- what the checkpoints keep

def test_checkpoints_keep_the_resolved_recipe_and_its_decoding(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.json")
    train.main(recipe_argv(data, recipe, tmp_path / "run", "--max_train_steps", "3", "--checkpointing_steps", "1",
                           "--checkpoints_total_limit", "1", "--ema_decay", "0.5"))
    for ckpt in ("final_checkpt", "checkpoint-3", "checkpoint-3/ema"):
        saved = json.loads((tmp_path / "run" / ckpt / "recipe.json").read_text())
        assert saved["decoding"] == DecodingConfig(**DECODING).to_dict()
        assert json.loads((tmp_path / "run" / ckpt / "decoding.json").read_text()) == saved["decoding"]
        assert saved["model"] == json.loads((tmp_path / "run" / ckpt / "config.json").read_text())
        args = saved["train"]
        assert (args["max_train_steps"], args["learning_rate"], args["checkpointing_steps"]) == (3, 3e-3, "1")
        assert args["recipe"] == str(recipe) and args["output_dir"] == str(tmp_path / "run")
        assert set(args) == set(vars(train.parse_args([])))  # every flag, none dropped
    model = STMaskGIT.from_pretrained(tmp_path / "run" / "final_checkpt")
    assert model.decoding == DecodingConfig(**DECODING) and model.copy_head.copy_bias == 2.0


def test_the_saved_decoding_leaves_training_alone(data, tmp_path):
    """The copy head adds copy_bias in its forward pass: set only while saving, it changes no step of training,
    and a run without a recipe keeps the default decoding."""
    recipe = write_recipe(tmp_path / "r.json")
    train.main(recipe_argv(data, recipe, tmp_path / "recipe", "--max_train_steps", "4", "--checkpointing_steps", "2",
                           "--eval_every_n_steps", "1"))
    train.main(train_argv(data, tmp_path / "flags", "--max_train_steps", "4", "--checkpointing_steps", "2",
                          "--eval_every_n_steps", "1"))
    assert_same_weights(load_weights(tmp_path / "recipe" / "final_checkpt"),
                        load_weights(tmp_path / "flags" / "final_checkpt"))
    plain = tmp_path / "flags" / "final_checkpt"
    assert json.loads((plain / "decoding.json").read_text()) == DecodingConfig().to_dict()
    saved = json.loads((plain / "recipe.json").read_text())
    assert saved["decoding"] == DecodingConfig().to_dict() and saved["train"]["recipe"] is None
    assert saved["train"]["genie_config"] == str(data["config"])


def test_genie_config_overrides_the_recipe_s_model(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.json", model={**TINY, "d_model": 64, "copy_radius": 1})
    train.main(recipe_argv(data, recipe, tmp_path / "run", "--genie_config", str(data["config"]),
                           "--max_train_steps", "0"))
    assert GenieConfig.from_pretrained(tmp_path / "run" / "final_checkpt" / "config.json").d_model == TINY["d_model"]


def test_a_copy_bias_without_a_copy_head_stops_before_training(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.json", model=TINY)
    with pytest.raises(SystemExit, match=r"r.json: decoding.copy_bias 2.0 needs a model with a copy head"):
        train.main(recipe_argv(data, recipe, tmp_path / "run"))
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------- the shipped recipes' models

@pytest.mark.parametrize("cpu_model, gpu_model", [
    (CONFIG_DIR / "sample_world.json", CONFIG_DIR / "gpu_world.json"),
    (RECIPES / "sample_world.json", RECIPES / "gpu_world.json")])
def test_gpu_models_are_the_cpu_models_scaled(cpu_model, gpu_model):
    """run_gpu.sh's models differ from the CPU defaults in size alone (depth, width and the number of heads, at the
    CPU model's head width), so the two recipes' numbers compare."""
    size = ("num_layers", "num_heads", "d_model")
    cpu, gpu = (model_dict(path) for path in (cpu_model, gpu_model))
    assert {k: v for k, v in gpu.items() if k not in size} == {k: v for k, v in cpu.items() if k not in size}
    assert gpu["d_model"] // gpu["num_heads"] == cpu["d_model"] // cpu["num_heads"]
    config, _ = load_model_config(gpu_model)
    assert (config.num_layers, config.d_model) == (8, 256)
    params = sum(p.numel() for p in STMaskGIT(config).parameters())
    assert 9.9e6 < params < 10.1e6  # the README's 10.0 M


def test_latent_action_config_is_the_main_model_with_latent_actions():
    """sample_world_latent.json is the main command's model with the LAM's 8 latent actions in place of the real
    action streams, so the two kinds of action model compare at the same architecture."""
    real = ("action_names", "action_dim", "action_step_mean", "time_reverse_ratio", "time_reverse_swaps")
    main, latent = model_dict(RECIPES / "sample_world.json"), model_dict(CONFIG_DIR / "sample_world_latent.json")
    assert latent == {**{k: v for k, v in main.items() if k not in real}, "num_latent_actions": 8}
    config = GenieConfig.from_pretrained(CONFIG_DIR / "sample_world_latent.json")
    assert config.uses_actions and config.action_names is None and config.num_latent_actions == 8


def model_dict(path: Path) -> dict:
    """A model config file's keys, or a recipe's model section."""
    d = json.loads(path.read_text())
    return d["model"] if "model" in d else d



# ---------------------------------------------------------------- the shell jobs

def train_call(script: str, tmp_path: Path, **env) -> list:
    """The train.py arguments `script` runs with the environment `env`, read from a stand-in Python that records
    them and stops the job there (it answers the GPU and data checks before)."""
    fake = tmp_path / "python"
    fake.write_text("#!/usr/bin/env bash\n"
                    "case \"$1\" in -c|-m) exit 0 ;; train.py) shift; printf '%s\\n' \"$@\" > \"$ARGS_FILE\"; "
                    "exit 3 ;; esac\nexit 1\n")
    fake.chmod(0o755)
    for split in ("train", "val"):
        (tmp_path / "world" / split).mkdir(parents=True, exist_ok=True)
        (tmp_path / "world" / split / "metadata.json").write_text("{}")
    base = {"PATH": os.environ["PATH"], "PY": str(fake), "ARGS_FILE": str(tmp_path / "args"),
            "SAMPLE_DIR": str(tmp_path / "world"), "GPU_DIR": str(tmp_path / "world"), "SKIP_BUILD": "1",
            "OUT": str(tmp_path / "out")}
    proc = subprocess.run(["bash", str(REPO / script), "--seed", "7"], env={**base, **env}, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 3, proc.stderr
    return (tmp_path / "args").read_text().splitlines()


def test_run_sample_trains_its_recipe_with_the_variables_overrides(tmp_path):
    world = tmp_path / "world"
    common = ["--train_data_dir", f"{world}/train", "--val_data_dir", f"{world}/val", "--output_dir",
              str(tmp_path / "out"), "--resume_from_checkpoint", "latest", "--seed", "7"]
    assert train_call("run_sample.sh", tmp_path) == ["--recipe", "recipes/sample_world.json", *common]
    assert train_call("run_sample.sh", tmp_path, GENIE_CONFIG="my config.json", WEIGHT_DECAY="0.1",
                      RECIPE="mine.json") == ["--recipe", "mine.json", "--genie_config", "my config.json",
                                              "--weight_decay", "0.1", *common]


def test_run_gpu_trains_its_recipe_with_the_variables_overrides(tmp_path):
    args = train_call("run_gpu.sh", tmp_path)
    assert args[:2] == ["--recipe", "recipes/gpu_world.json"] and args[-2:] == ["--seed", "7"]
    assert not {"--max_train_steps", "--num_warmup_steps", "--learning_rate", "--compile"} & set(args)
    args = train_call("run_gpu.sh", tmp_path, STEPS="40", LR="1e-3", COMPILE="1")
    assert args[-9:] == ["--max_train_steps", "40", "--num_warmup_steps", "2", "--learning_rate", "1e-3",
                         "--compile", "--seed", "7"]
    assert train_call("run_gpu.sh", tmp_path, WARMUP="5")[-4:] == ["--num_warmup_steps", "5", "--seed", "7"]
