"""MaskGIT sampler: fills every mask, keeps given tokens, follows the schedule, temperature divides the logits."""
import math

import pytest
import torch
from einops import rearrange

from genie.factorization import unfactorize_token_ids
from genie.sampling import Prediction, maskgit_sample, sample_factored_tokens, sample_mixture_tokens
from genie.sampling import num_masked_after_step

V, F_ = 8, 2
MASK = V ** F_


class RandomLogits:
    """logits_fn returning fresh random factored logits (B, V, F, H, W) and recording its inputs."""

    def __init__(self, seed=0):
        self.g = torch.Generator().manual_seed(seed)
        self.inputs = []

    def __call__(self, frame_BHW):
        self.inputs.append(frame_BHW.clone())
        B, H, W = frame_BHW.shape
        return torch.randn(B, V, F_, H, W, generator=self.g) * 3


@pytest.mark.parametrize("unmask_mode", ["random", "greedy"])
@pytest.mark.parametrize("steps", [1, 2, 3, 5])
@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_fills_every_mask_keeps_given_tokens_and_follows_schedule(unmask_mode, steps, temperature):
    B, H, W = 3, 4, 4
    g = torch.Generator().manual_seed(1)
    frame = torch.randint(0, MASK, (B, H, W), generator=g)
    given = torch.rand(B, H, W, generator=g) < 0.25
    frame = frame.masked_fill(~given, MASK)
    logits_fn = RandomLogits()
    sample, first_logits = maskgit_sample(logits_fn, frame, MASK, steps, temperature, unmask_mode,
                                          torch.Generator().manual_seed(2))
    assert sample.shape == frame.shape and sample.dtype == frame.dtype
    assert (sample != MASK).all() and (sample >= 0).all() and (sample < MASK).all()
    assert torch.equal(sample[given], frame[given])
    assert len(logits_fn.inputs) == steps
    assert torch.equal(logits_fn.inputs[0], frame)
    for step, seen in enumerate(logits_fn.inputs[1:]):
        # after step `step` the schedule leaves this many masked (never more than were masked before)
        still = (seen == MASK).flatten(1).sum(1)
        expected = torch.clamp((~given).flatten(1).sum(1), max=num_masked_after_step(step, steps, H * W))
        assert torch.equal(still, expected)
        # revealed tokens stay fixed in later steps
        revealed = seen != MASK
        assert torch.equal(sample[revealed], seen[revealed])
    assert first_logits.shape == (B, V, F_, H, W)


def test_argmax_at_temperature_zero():
    logits = torch.randn(2, V, F_, 3, 3, generator=torch.Generator().manual_seed(0))
    frame = torch.full((2, 3, 3), MASK)
    sample, first = maskgit_sample(lambda f: logits, frame, MASK, 1, temperature=0.0)
    expected = logits.argmax(1)[:, 0] + V * logits.argmax(1)[:, 1]
    assert torch.equal(sample, expected)
    assert torch.equal(first, logits)


def test_temperature_divides_the_logits():
    # factor 0 has logits (0, ln 3) over two values (others -inf); factor 1 always value 0
    logits = torch.full((1, V, F_, 1), -float("inf"))
    logits[0, 0, 0], logits[0, 1, 0], logits[0, 0, 1] = 0.0, math.log(3), 0.0
    logits_BVFS = logits.expand(20000, -1, -1, -1)
    for temperature, p_one in ((1.0, 0.75), (0.5, 0.9), (2.0, 3 ** 0.5 / (1 + 3 ** 0.5))):
        ids, conf = sample_factored_tokens(logits_BVFS, temperature, torch.Generator().manual_seed(0))
        freq = (ids == 1).float().mean().item()
        assert abs(freq - p_one) < 0.015, (temperature, freq, p_one)
        # confidence is the untempered probability of the drawn value
        torch.testing.assert_close(conf[ids == 1], torch.full_like(conf[ids == 1], 0.75))


def test_greedy_unmasking_reveals_the_most_confident_first():
    S = 16
    confident = torch.zeros(1, V, F_, 4, 4)
    strength = torch.arange(S, dtype=torch.float32).view(4, 4)  # token s has peak logit s on value 0
    confident[0, 0] = strength
    logits_fn = RandomLogits()
    calls = []

    def fn(frame):
        calls.append(frame.clone())
        return confident if len(calls) == 1 else logits_fn(frame)

    maskgit_sample(fn, torch.full((1, 4, 4), MASK), MASK, 2, unmask_mode="greedy")
    kept_masked = num_masked_after_step(0, 2, S)
    revealed = (calls[1] != MASK).flatten()
    assert torch.equal(revealed, torch.arange(S) >= kept_masked)


def test_same_generator_same_samples_and_different_seeds_differ():
    frame = torch.full((4, 4, 4), MASK)
    logits = torch.randn(4, V, F_, 4, 4, generator=torch.Generator().manual_seed(0))
    runs = [maskgit_sample(lambda f: logits, frame, MASK, 3, 1.0, generator=torch.Generator().manual_seed(s))[0]
            for s in (5, 5, 6)]
    assert torch.equal(runs[0], runs[1])
    assert not torch.equal(runs[0], runs[2])


def test_unfactorized_ids_use_factor_0_as_least_significant():
    logits = torch.full((1, V, F_, 1), -1e4)
    logits[0, 3, 0] = 0  # factor 0 = 3
    logits[0, 5, 1] = 0  # factor 1 = 5
    ids, _ = sample_factored_tokens(logits)
    assert ids.item() == 3 + 5 * V == unfactorize_token_ids(torch.tensor([3, 5]), F_, V).item()


def test_bad_arguments():
    frame = torch.full((1, 2, 2), MASK)
    fn = RandomLogits()
    with pytest.raises(ValueError, match="maskgit_steps"):
        maskgit_sample(fn, frame, MASK, 0)
    with pytest.raises(ValueError, match="unmask_mode"):
        maskgit_sample(fn, frame, MASK, 2, unmask_mode="confidence")
    with pytest.raises(ValueError, match="temperature"):
        maskgit_sample(fn, frame, MASK, 2, temperature=-1.0)


def test_greedy_steps_take_a_predictions_mode_and_its_probabilities_as_confidence():
    B, H, W = 2, 4, 4
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(B, V, F_, H, W, generator=g) * 3
    mode = torch.randint(0, MASK, (B, H, W), generator=g)
    probs = torch.rand(B, H, W, generator=g)
    calls = []

    def logits_fn(frame_BHW):
        calls.append(frame_BHW.clone())
        return Prediction(logits, mode, probs)

    frame = torch.full((B, H, W), MASK)
    sample, first = maskgit_sample(logits_fn, frame, MASK, 1)
    assert torch.equal(sample, mode) and torch.equal(first, logits)
    # two greedy-order steps: the first reveals the masked tokens of highest mode probability
    calls.clear()
    maskgit_sample(logits_fn, frame, MASK, 2, unmask_mode="greedy")
    revealed = calls[1] != MASK
    S = H * W
    kept = S - num_masked_after_step(0, 2, S)
    assert torch.equal(revealed.flatten(1), probs.flatten(1) >= probs.flatten(1).topk(kept, dim=1).values[:, -1:])
    assert torch.equal(calls[1][revealed], mode[revealed])
    # at a temperature the factors are drawn from the logits, the mode ignored
    drawn, _ = maskgit_sample(logits_fn, frame, MASK, 1, temperature=1.0, generator=torch.Generator().manual_seed(0))
    plain, _ = maskgit_sample(lambda f: logits, frame, MASK, 1, temperature=1.0,
                              generator=torch.Generator().manual_seed(0))
    assert torch.equal(drawn, plain) and not torch.equal(drawn, mode)


def test_steps_at_a_temperature_draw_from_the_mixture_parts_when_given():
    B, H, W, K = 2, 3, 3, 4
    g = torch.Generator().manual_seed(5)
    logits = torch.randn(B, V, F_, H, W, generator=g)
    readout = torch.randn(B, V, F_, H, W, generator=g) * 3
    log_weights = torch.randn(B, H, W, K + 1, generator=g).log_softmax(-1)
    sources = torch.randint(0, MASK, (B, H, W, K), generator=g)
    mode = torch.randint(0, MASK, (B, H, W), generator=g)
    prediction = Prediction(logits, mode, torch.rand(B, H, W, generator=g), log_weights, sources, readout)
    frame = torch.full((B, H, W), MASK)
    drawn, _ = maskgit_sample(lambda f: prediction, frame, MASK, 1, temperature=1.0,
                              generator=torch.Generator().manual_seed(0))
    direct, _ = sample_mixture_tokens(log_weights, sources, rearrange(readout, "B V F H W -> B H W V F"), 1.0,
                                      torch.Generator().manual_seed(0))
    assert torch.equal(drawn, direct)
    greedy, _ = maskgit_sample(lambda f: prediction, frame, MASK, 1)
    assert torch.equal(greedy, mode)  # greedy steps still take the mode
    with pytest.raises(ValueError, match="temperature"):
        sample_mixture_tokens(log_weights, sources, readout, 0.0)
