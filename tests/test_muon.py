"""common/muon.py: the Newton-Schulz orthogonalization, the Muon and AdamW steps, and `train.py --optimizer muon`."""
import math

import pytest
import torch

import train
from common.muon import MuonAdamW, build_optimizer, orthogonalize
from common.train_state import load_training_checkpoint
from tests.test_train import assert_same_weights, load_weights, masked_val_loss, tiny_data, train_argv  # noqa: F401
from genie import GenieConfig, STMaskGIT

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("shape", [(64, 24), (24, 64), (32, 32)])
def test_orthogonalize_keeps_the_singular_vectors_and_flattens_the_spectrum(shape):
    g = torch.randn(shape, generator=torch.Generator().manual_seed(0)) * 7.0
    g[:, 0] *= 30  # one dominant direction, as in a raw gradient
    o = orthogonalize(g)
    assert o.shape == g.shape
    singular = torch.linalg.svdvals(o)
    assert singular.min() > 0.6 and singular.max() < 1.25, singular
    u, _, vh = torch.linalg.svd(g, full_matrices=False)
    exact = u @ vh
    cosine = (o * exact).sum() / (o.norm() * exact.norm())
    assert cosine > 0.97, cosine


def test_adamw_groups_take_torch_adamw_steps():
    torch.manual_seed(0)
    a = [torch.nn.Parameter(torch.randn(5, 3)), torch.nn.Parameter(torch.randn(4))]
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    ours = MuonAdamW([{"params": a[:1], "weight_decay": 0.1}, {"params": a[1:], "weight_decay": 0.0}],
                     lr=1e-2, betas=(0.8, 0.95), eps=1e-6)
    ref = torch.optim.AdamW([{"params": b[:1], "weight_decay": 0.1}, {"params": b[1:], "weight_decay": 0.0}],
                            lr=1e-2, betas=(0.8, 0.95), eps=1e-6, foreach=False)
    for step in range(5):
        grads = [torch.randn_like(p) for p in a]
        for params in (a, b):
            for p, g in zip(params, grads):
                p.grad = g.clone()
        ours.step()
        ref.step()
        for p, q in zip(a, b):
            torch.testing.assert_close(p, q, atol=1e-6, rtol=1e-6)


def test_muon_step_is_the_scaled_orthogonalized_momentum():
    torch.manual_seed(0)
    w = torch.nn.Parameter(torch.randn(48, 16))
    before = w.detach().clone()
    lr, wd = 1e-2, 0.05
    opt = MuonAdamW([{"params": [w], "muon": True, "weight_decay": wd}], lr=lr)
    w.grad = torch.randn(48, 16)
    opt.step()
    # first step: the Nesterov momentum is a multiple of the gradient, and orthogonalization ignores the scale
    expected = before * (1 - lr * wd) - lr * 0.2 * math.sqrt(48) * orthogonalize(w.grad)
    torch.testing.assert_close(w.detach(), expected)
    step_rms = (w.detach() - before * (1 - lr * wd)).pow(2).mean().sqrt()
    assert 0.15 * lr < step_rms < 0.25 * lr  # AdamW's typical step RMS: the same lr serves both kinds of groups
    assert torch.equal(opt.state[w]["momentum_buffer"], 0.05 * w.grad)


def test_muon_groups_take_only_matrices():
    with pytest.raises(ValueError, match="2-D"):
        MuonAdamW([{"params": [torch.nn.Parameter(torch.zeros(4))], "muon": True}])


def test_build_optimizer_groups():
    hidden, embed, bias = (torch.nn.Parameter(torch.zeros(shape)) for shape in ((4, 3), (5, 3), (3,)))
    muon = build_optimizer([hidden, embed, bias], [hidden, bias], "muon", lr=1e-2, weight_decay=0.1)
    assert [(g.get("muon", False), len(g["params"]), g["weight_decay"]) for g in muon.param_groups] == [
        (True, 1, 0.1), (False, 1, 0.1), (False, 1, 0.0)]  # 1-D params never take Muon steps nor weight decay
    adamw = build_optimizer([hidden, embed, bias], [hidden], "adamw", lr=1e-2, weight_decay=0.1)
    assert isinstance(adamw, torch.optim.AdamW) and [len(g["params"]) for g in adamw.param_groups] == [2, 1]
    with pytest.raises(ValueError, match="unknown optimizer 'sgd'"):
        build_optimizer([hidden], [], "sgd", lr=1e-2, weight_decay=0.0)


def test_train_with_muon_learns_and_resumes_exactly(tiny_data, tmp_path):
    full, resumed = tmp_path / "full", tmp_path / "resumed"
    extra = ("--optimizer", "muon", "--max_train_steps", "30", "--checkpointing_steps", "10",
             "--weight_decay", "0.05", "--learning_rate", "1e-2")
    train.main(train_argv(tiny_data, full, *extra))
    config = GenieConfig.from_pretrained(tiny_data["config"])
    torch.manual_seed(0)
    untrained = STMaskGIT(config)
    untrained.init_weights()
    before = masked_val_loss(untrained, tiny_data["val"], config)
    after = masked_val_loss(STMaskGIT.from_pretrained(full / "final_checkpt"), tiny_data["val"], config)
    assert after < 0.7 * before, (before, after)
    state = load_training_checkpoint(full / "checkpoint-10")["optimizer"]
    muon_groups = [g for g in state["param_groups"] if g.get("muon")]
    assert len(muon_groups) == 1 and len(muon_groups[0]["params"]) == 6 * config.num_layers  # (qkv, proj) x 2, fc1, fc2

    train.main(train_argv(tiny_data, resumed, *extra, "--resume_from_checkpoint", str(full / "checkpoint-10")))
    assert_same_weights(load_weights(full / "final_checkpt"), load_weights(resumed / "final_checkpt"))
    with pytest.raises(SystemExit, match="trained with --optimizer muon, not adamw"):
        train.main(train_argv(tiny_data, tmp_path / "other", "--max_train_steps", "30",
                              "--resume_from_checkpoint", str(full / "checkpoint-10")))
