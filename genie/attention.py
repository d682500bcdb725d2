"""Multi-head self-attention with the published GENIE parameter layout, on F.scaled_dot_product_attention.

Parameters (docs/formats.md §3): `qkv` (3d, d) whose output splits as (3, heads, head_dim), `proj` (d, d) and, with
qk_norm, one LayerNorm `norm` over head_dim applied to both q and k. The published weights were trained with
xformers' memory-efficient attention: q and k are normalized first and the softmax scale is applied afterwards
inside the attention kernel, which is what `scale=` of scaled_dot_product_attention does here. (The published
non-xformers fallback scaled q before the norm, which cancels the scale; the trained weights never saw that path.)
attn_drop, 0 in every published config and unused by the published xformers path, drops attention weights in
training.
"""
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from genie.rope import apply_rope


def attention_scale(head_dim: int, use_mup: bool) -> float:
    """Softmax scale: head_dim^-0.5, or 8 / head_dim under muP (equal at head_dim 64)."""
    return 8 / head_dim if use_mup else head_dim ** -0.5


# bf16 on CPU, sequences of at most this many keys (the temporal attention) take the written-out path; longer ones
# are faster in torch's fused kernel
CPU_BF16_MATH_MAX_KEYS = 64


class SelfAttention(nn.Module):
    def __init__(self, d_model: int, num_heads: int, qkv_bias: bool = False, proj_bias: bool = True,
                 qk_norm: bool = False, use_mup: bool = False, attn_drop: float = 0.0) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = d_model // num_heads
        self.scale = attention_scale(self.head_dim, use_mup)
        self.attn_drop = attn_drop
        self.qkv = nn.Linear(d_model, 3 * d_model, bias=qkv_bias)
        self.proj = nn.Linear(d_model, d_model, bias=proj_bias)
        self.qk_norm = qk_norm
        if qk_norm:
            self.norm = nn.LayerNorm(self.head_dim, eps=1e-5)
        # bf16 on CPU: the written-out path for short sequences (`_attend_bf16_cpu`); `set_cpu_bf16_math` turns it
        # off per model (benchmarks/bench_train.py compares the two)
        self.cpu_bf16_math = True

    def project_qkv(self, x_BNC: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, N, C) -> q, k, v, each (B, heads, N, head_dim)."""
        qkv_3BhNd = rearrange(self.qkv(x_BNC), "B N (three h d) -> three B h N d", three=3, h=self.num_heads)
        q, k, v = qkv_3BhNd.unbind(0)
        if self.qk_norm:
            # under autocast LayerNorm runs in fp32; the attention kernel wants q, k, v in one dtype
            q = self.norm(q).to(v.dtype)
            k = self.norm(k).to(v.dtype)
        return q, k, v

    def project_kv(self, x_BNC: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Keys and values only, each (B, heads, N, head_dim): skips the query third of the qkv projection."""
        C = x_BNC.shape[-1]
        bias = None if self.qkv.bias is None else self.qkv.bias[C:]
        kv_2BhNd = rearrange(F.linear(x_BNC, self.qkv.weight[C:], bias), "B N (two h d) -> two B h N d", two=2,
                             h=self.num_heads)
        k, v = kv_2BhNd.unbind(0)
        if self.qk_norm:
            k = self.norm(k).to(v.dtype)
        return k, v

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: Optional[torch.Tensor] = None,
               is_causal: bool = False) -> torch.Tensor:
        """q (B, heads, Nq, head_dim), k and v (B, heads, Nk, head_dim) -> projected output (B, Nq, C).

        attn_mask: optional bool (Nq, Nk), True where a query may attend to a key.
        """
        dropout_p = self.attn_drop if self.training else 0.0
        if (self.cpu_bf16_math and q.device.type == "cpu" and q.dtype == torch.bfloat16
                and k.shape[-2] <= CPU_BF16_MATH_MAX_KEYS):
            x_BhNd = self._attend_bf16_cpu(q, k, v, attn_mask, is_causal, dropout_p)
        else:
            x_BhNd = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, is_causal=is_causal,
                                                    dropout_p=dropout_p, scale=self.scale)
        return self.proj(rearrange(x_BhNd, "B h N d -> B N (h d)"))

    def _attend_bf16_cpu(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                         attn_mask: Optional[torch.Tensor], is_causal: bool, dropout_p: float) -> torch.Tensor:
        """Attention written out for bf16 on CPU: (B, h, Nq, d) -> (B, h, Nq, d).

        torch's fused CPU attention kernel is slow in bf16 for many short sequences (the temporal attention: B*S
        sequences of T frames; ~3x slower forward + backward at T = 16), while for the spatial attention (S = 256
        keys) it is the faster one; two bf16 matmuls with an fp32 softmax in between use the CPU's native bf16 dot
        products instead (benchmarks/bench_train.py --mixed_precision compare).
        """
        scores = (q @ k.transpose(-1, -2)).float() * self.scale
        if is_causal:
            future = torch.ones(scores.shape[-2:], dtype=torch.bool, device=q.device).triu(1)  # top-left, as SDPA
            scores = scores.masked_fill(future, float("-inf"))
        if attn_mask is not None:
            scores = scores.masked_fill(~attn_mask, float("-inf"))
        probs = F.dropout(scores.softmax(dim=-1), p=dropout_p) if dropout_p else scores.softmax(dim=-1)
        return probs.to(v.dtype) @ v

    def forward(self, x_BNC: torch.Tensor, causal: bool = False,
                rope: Optional[Tuple[torch.Tensor, torch.Tensor]] = None) -> torch.Tensor:
        """(B, N, C) -> (B, N, C); rope: optional (cos, sin) tables (N, head_dim) that rotate q and k (genie/rope.py)."""
        q, k, v = self.project_qkv(x_BNC)
        if rope is not None:
            q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        return self.attend(q, k, v, is_causal=causal)

    def attend_targets(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, context_k: torch.Tensor,
                       context_v: torch.Tensor) -> torch.Tensor:
        """Teacher-forced targets: target i attends to context positions 0..i and to itself only.

        q, k, v: (B, heads, n, head_dim) of the n targets; context_k, context_v: (B, heads, n, head_dim).
        Returns the projected output (B, n, C). Equal to scaled_dot_product_attention over
        cat([context, targets]) with mask [tril, eye]; written out because that needs a (B, heads, 2n, head_dim)
        copy of the keys and values at every step and the slow masked kernel.
        """
        n = q.shape[2]
        q, k = q.float() * self.scale, k.float()  # fp32 scores and softmax, like the fused kernels (no-op in fp32)
        future = torch.ones(n, n, dtype=torch.bool, device=q.device).triu(1)
        scores_ctx = (q @ context_k.float().transpose(-1, -2)).masked_fill_(future, float("-inf"))
        score_self = (q * k).sum(-1, keepdim=True)
        probs = torch.cat([scores_ctx, score_self], dim=-1).softmax(dim=-1)
        x_BhNd = (probs[..., :n] @ context_v.float() + probs[..., n:] * v.float()).to(v.dtype)
        return self.proj(rearrange(x_BhNd, "B h N d -> B N (h d)"))


def set_cpu_bf16_math(model: nn.Module, enabled: bool) -> None:
    """Choose, for every attention layer of `model`, the written-out bf16 CPU path (True) or torch's fused kernel."""
    for module in model.modules():
        if isinstance(module, SelfAttention):
            module.cpu_bf16_math = enabled
