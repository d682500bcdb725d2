"""Muon for a transformer's hidden weight matrices and AdamW for every other parameter, as one torch optimizer.

Muon (K. Jordan et al., 2024) keeps a momentum of each matrix's gradient and steps along its nearest
semi-orthogonal matrix (the same singular vectors, every singular value 1), found with a few Newton-Schulz
iterations. Every direction of the update then moves at the same rate, where a raw momentum step is dominated by a
few large singular directions. The orthogonalized step is scaled by 0.2 * sqrt(max(rows, cols)) so that its RMS
matches a typical AdamW step (J. Liu et al., "Muon is scalable for LLM training", 2025): one learning rate, schedule
and weight decay serve both kinds of groups, and `--optimizer muon` needs no other retuning to be tried.

Embeddings, output heads, biases and norms stay on AdamW: they are not linear maps between hidden states, which is
what the orthogonalization assumes.
"""
import math
from typing import Iterable

import torch

# The quintic iteration's coefficients (Jordan et al.): converges fast from a spectral norm <= 1 to singular values
# in about [0.7, 1.2], which is all the step needs.
NS_COEFFICIENTS = (3.4445, -4.7750, 2.0315)


def orthogonalize(g_AB: torch.Tensor, steps: int = 5, eps: float = 1e-7) -> torch.Tensor:
    """The nearest semi-orthogonal matrix to g_AB (A x B), approximately, by Newton-Schulz; same shape."""
    a, b, c = NS_COEFFICIENTS
    x = g_AB.float() / (g_AB.float().norm() + eps)  # Frobenius norm >= spectral norm: the iteration converges
    wide = x.T if x.shape[0] > x.shape[1] else x  # iterate on the smaller Gram matrix
    for _ in range(steps):
        gram = wide @ wide.T
        wide = a * wide + (b * gram + c * gram @ gram) @ wide
    return (wide.T if x.shape[0] > x.shape[1] else wide).to(g_AB.dtype)


class MuonAdamW(torch.optim.Optimizer):
    """Parameter groups with "muon": True (2-D parameters only) take Muon steps, the others AdamW steps.

    Both use the group's lr and decoupled weight_decay; Muon groups also read momentum (Nesterov), AdamW groups
    betas and eps. State per parameter: Muon "momentum_buffer"; AdamW "step", "exp_avg", "exp_avg_sq".
    """

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-8, weight_decay: float = 0.0,
                 momentum: float = 0.95, ns_steps: int = 5):
        if lr < 0 or weight_decay < 0 or not 0 <= momentum < 1:
            raise ValueError(f"MuonAdamW: invalid lr {lr}, weight_decay {weight_decay} or momentum {momentum}")
        defaults = dict(lr=lr, betas=tuple(betas), eps=eps, weight_decay=weight_decay, momentum=momentum,
                        ns_steps=ns_steps, muon=False)
        super().__init__(params, defaults)
        for group in self.param_groups:
            if group["muon"] and any(p.dim() != 2 for p in group["params"]):
                raise ValueError("MuonAdamW: a Muon group may hold only 2-D (matrix) parameters, got shapes "
                                 f"{[tuple(p.shape) for p in group['params'] if p.dim() != 2]}")

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if group["weight_decay"]:
                    p.mul_(1 - group["lr"] * group["weight_decay"])
                (self._muon_step if group["muon"] else self._adamw_step)(p, group)
        return loss

    def _muon_step(self, p: torch.Tensor, group: dict) -> None:
        state = self.state[p]
        if "momentum_buffer" not in state:
            state["momentum_buffer"] = torch.zeros_like(p)
        buf = state["momentum_buffer"]
        buf.lerp_(p.grad, 1 - group["momentum"])
        update = orthogonalize(p.grad.lerp(buf, group["momentum"]), steps=group["ns_steps"])
        p.add_(update, alpha=-group["lr"] * 0.2 * math.sqrt(max(p.shape)))

    def _adamw_step(self, p: torch.Tensor, group: dict) -> None:
        state = self.state[p]
        if "step" not in state:
            state["step"] = torch.zeros((), dtype=torch.float32)
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
        beta1, beta2 = group["betas"]
        state["step"] += 1
        t = state["step"].item()
        state["exp_avg"].lerp_(p.grad, 1 - beta1)
        state["exp_avg_sq"].mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
        denom = (state["exp_avg_sq"].sqrt() / math.sqrt(1 - beta2 ** t)).add_(group["eps"])
        p.addcdiv_(state["exp_avg"], denom, value=-group["lr"] / (1 - beta1 ** t))


def build_optimizer(params: Iterable[torch.nn.Parameter], hidden_matrices: Iterable[torch.nn.Parameter], name: str,
                    lr: float, weight_decay: float, betas=(0.9, 0.999), eps: float = 1e-8, momentum: float = 0.95,
                    fused: bool = False) -> torch.optim.Optimizer:
    """The optimizer `train.py --optimizer` names, over the trainable `params`.

    "adamw": torch's AdamW (`fused` uses its fused kernel); "muon": MuonAdamW, Muon for `hidden_matrices` (2-D
    parameters among `params`) and AdamW for the rest. Weight decay applies to parameters with >= 2 dimensions
    (matrices and embeddings, as nanoGPT does), never to biases and norm weights.
    """
    params = [p for p in params if p.requires_grad]
    matrices = [p for p in params if p.dim() >= 2]
    no_decay = {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0}
    if name == "adamw":
        return torch.optim.AdamW([{"params": matrices, "weight_decay": weight_decay}, no_decay], lr=lr, betas=betas,
                                 eps=eps, fused=fused or None)
    if name != "muon":
        raise ValueError(f"unknown optimizer {name!r}: use adamw or muon")
    hidden = {id(p) for p in hidden_matrices if p.dim() == 2}
    groups = [{"params": [p for p in matrices if id(p) in hidden], "weight_decay": weight_decay, "muon": True},
              {"params": [p for p in matrices if id(p) not in hidden], "weight_decay": weight_decay}, no_decay]
    return MuonAdamW(groups, lr=lr, betas=betas, eps=eps, momentum=momentum)
