"""Cost of the previous-frame pointer (genie/copy_head.py) next to the plain readout and the dense mixture.

    python benchmarks/bench_copy_head.py                       # sample-world shape: d_model 128, 2 x 512, radius 2
    python benchmarks/bench_copy_head.py --radius 4 --num_tokens 8192

Three ways to turn readout logits (N, 512, 2) into log-probabilities, timed side by side on the same inputs:
  plain   log_softmax of the readout (a model without the pointer)
  sparse  CopyHead.forward: touches only the <= K values the neighbours hold (sorted rows, no (N, F, V) buffers
          besides the output)
  dense   genie.reference.dense_copy_mixture: the mixture written over every value through a (N, K, F, V) one-hot
Each is timed for inference (no autograd) and for training (forward + backward). Prints milliseconds, the ratios
sparse / plain and dense / sparse, and the largest difference between sparse and dense. Then what greedy decoding
adds at inference: CopyHead.mode (the mixture's most probable whole token, the default) next to the factor-wise
argmax of the sparse mixture (the plain argmax it replaced) and the mode with copies from the single most weighted
neighbour (`--greedy_tokens best_neighbour`); and what sampling at temperature 1 adds:
genie.sampling.sample_mixture_tokens (whole tokens) next to sample_factored_tokens over the mixture's marginals
(what it replaced), and next to the same draws with the greedy mode computed too (which sampling never reads, so
inference at a temperature skips it: `STMaskGIT.predict_frames(greedy=False)`).
"""
import argparse
import sys
import time

import torch
from einops import rearrange

from common.cli import add_num_threads_arg, apply_cpu_settings, non_negative_int, positive_int, run_main
from genie.copy_head import CopyHead
from genie.reference import dense_copy_mixture
from genie.sampling import sample_factored_tokens, sample_mixture_tokens


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="Time the copy head's mixture against the plain readout and the dense "
                                            "mixture.", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--num_tokens", type=positive_int, default=2048, help="Predicted tokens per call (N).")
    p.add_argument("--radius", type=non_negative_int, default=2, help="Copy radius r (K = (2r+1)^2 neighbours).")
    p.add_argument("--d_model", type=positive_int, default=128, help="Hidden size feeding the pointer's scores.")
    p.add_argument("--repeats", type=positive_int, default=5,
                   help="Timed calls per variant (after one warm-up call).")
    p.add_argument("--seed", type=non_negative_int, default=0, help="Seed of the random inputs.")
    add_num_threads_arg(p)
    return p.parse_args(argv)


def make_inputs(args: argparse.Namespace, V: int = 512, F: int = 2):
    """A head and inputs whose neighbours repeat values, as neighbouring tokens of a real frame do."""
    torch.manual_seed(args.seed)
    mask = V ** F
    head = CopyHead(args.d_model, args.radius, F, V, mask_token_id=mask)
    K = head.num_sources
    logits_NVF = torch.randn(args.num_tokens, V, F) * 2
    hidden_NC = torch.randn(args.num_tokens, args.d_model)
    sources_NK = torch.randint(0, 64, (args.num_tokens, K)) * 4099  # few distinct ids: repeats in both factors
    sources_NK[:, :K // 5] = mask  # neighbours outside the frame
    return head, logits_NVF, hidden_NC, sources_NK


def timed(fn, repeats: int, train: bool) -> float:
    """Mean seconds of fn() (forward only, or forward + backward of a sum)."""
    def call():
        with torch.set_grad_enabled(train):
            out = fn()
            if train:
                out.sum().backward()
    call()
    start = time.perf_counter()
    for _ in range(repeats):
        call()
    return (time.perf_counter() - start) / repeats


def main(argv=None) -> int:
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    head, logits_NVF, hidden_NC, sources_NK = make_inputs(args)
    print(f"N {args.num_tokens} tokens, K {head.num_sources} neighbours, 2 x 512 factors, "
          f"{torch.get_num_threads()} threads")
    for train in (False, True):
        logits = logits_NVF.clone().requires_grad_(train)
        variants = {"plain": lambda: logits.log_softmax(dim=1),
                    "sparse": lambda: head(logits, hidden_NC, sources_NK),
                    "dense": lambda: dense_copy_mixture(head, logits, hidden_NC, sources_NK)}
        seconds = {name: timed(fn, args.repeats, train) for name, fn in variants.items()}
        print(f"{'training (fwd+bwd)' if train else 'inference (no grad)':20s} "
              + "  ".join(f"{name} {1e3 * s:8.1f} ms" for name, s in seconds.items())
              + f"   sparse/plain {seconds['sparse'] / seconds['plain']:.2f}x"
              + f"   dense/sparse {seconds['dense'] / seconds['sparse']:.2f}x")
    factor_wise = timed(lambda: head(logits_NVF, hidden_NC, sources_NK).argmax(dim=1), args.repeats, False)
    joint = timed(lambda: head.forward_and_mode(logits_NVF, hidden_NC, sources_NK), args.repeats, False)
    head.best_neighbour_copies = True
    best = timed(lambda: head.forward_and_mode(logits_NVF, hidden_NC, sources_NK), args.repeats, False)
    head.best_neighbour_copies = False
    print(f"greedy decoding: mixture + factor-wise argmax {1e3 * factor_wise:8.1f} ms   mixture + joint mode "
          f"{1e3 * joint:8.1f} ms   + best-neighbour copies {1e3 * best:8.1f} ms   joint/factor-wise "
          f"{joint / factor_wise:.2f}x   best-neighbour/joint {best / joint:.2f}x")
    generator = torch.Generator().manual_seed(args.seed)
    marginals = timed(lambda: sample_factored_tokens(rearrange(head(logits_NVF, hidden_NC, sources_NK),
                                                               "N V F -> 1 V F N"), 1.0, generator),
                      args.repeats, False)
    whole = timed(lambda: sample_mixture_tokens(head.forward_and_log_weights(logits_NVF, hidden_NC, sources_NK)[1],
                                                sources_NK, logits_NVF, 1.0, generator), args.repeats, False)
    with_mode = timed(lambda: sample_mixture_tokens(head.forward_and_mode(logits_NVF, hidden_NC, sources_NK)[3],
                                                    sources_NK, logits_NVF, 1.0, generator), args.repeats, False)
    print(f"sampling (T = 1): mixture + factor-wise draws {1e3 * marginals:8.1f} ms   mixture + whole-token draws "
          f"{1e3 * whole:8.1f} ms   whole/factor-wise {whole / marginals:.2f}x   also computing the greedy mode "
          f"(as before) {1e3 * with_mode:8.1f} ms   without/with the mode {whole / with_mode:.2f}x")
    with torch.no_grad():
        diff = (head(logits_NVF, hidden_NC, sources_NK)
                - dense_copy_mixture(head, logits_NVF, hidden_NC, sources_NK)).abs().max().item()
    print(f"max |sparse - dense| log-probability: {diff:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main("bench_copy_head.py", main))
