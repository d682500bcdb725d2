"""The opt-in previous-frame pointer (genie/copy_head.py): its mixture, its sources, and the model paths using it."""
import json

import pytest
import safetensors.torch
import torch

from genie.decoding import GREEDY_TOKEN_CHOICES
from genie import GenieConfig, STMaskGIT
from genie.copy_head import CopyHead, previous_frames
from genie.factorization import factorize_token_ids, unfactorize_token_ids
from genie.inference import frame_slice, generate_frames, teacher_forced
from common.config import ConfigError
from genie.reference import dense_copy_mixture, generate_uncached, teacher_forced_uncached
from genie.sampling import sample_mixture_tokens

V, F_ = 64, 2
MASK = V ** F_


def tiny_copy_model(radius=1, seed=0, T=6, match=False) -> STMaskGIT:
    torch.manual_seed(seed)
    config = GenieConfig(num_layers=2, num_heads=4, d_model=32, T=T, S=16, image_vocab_size=V ** F_,
                         num_prompt_frames=2, qk_norm=True, copy_radius=radius, copy_match_input=match)
    model = STMaskGIT(config)
    model.init_weights()
    with torch.no_grad():  # logits and copy scores that differ clearly between tokens and neighbours
        model.out_x_proj.weight.normal_(0, 1.0)
        model.copy_head.score_proj.weight.normal_(0, 1.0)
        model.pos_embed_TSC.normal_(0, 1.0)
        if match:
            model.copy_head.match_proj.weight.normal_(0, 1.0)
    return model.eval()


def test_mixture_matches_a_hand_computation():
    torch.manual_seed(0)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    N, K = 5, 9
    logits, hidden = torch.randn(N, V, F_) * 3, torch.randn(N, 8)
    sources = torch.randint(0, MASK, (N, K))
    sources[0, :4] = MASK  # not offered
    sources[1] = MASK  # nothing offered: the readout alone
    sources[2, 3] = sources[2, 5]  # two neighbours with the same token add up
    out = head(logits, hidden, sources)

    scores = head.score_proj(hidden).detach()
    for n in range(N):
        offered = [k for k in range(K) if sources[n, k] != MASK]
        w = torch.softmax(torch.cat([scores[n, offered], scores[n, K:]]), dim=0)
        factors = factorize_token_ids(sources[n], F_, V)
        for f in range(F_):
            p = w[-1] * torch.softmax(logits[n, :, f], dim=0)
            for i, k in enumerate(offered):
                p[factors[k, f]] += w[i]
            torch.testing.assert_close(out[n, :, f].exp(), p, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(out[1], logits.log_softmax(dim=1)[1])
    assert torch.isfinite(out).all()
    with torch.no_grad():  # inference computes the same mixture in place
        torch.testing.assert_close(head(logits, hidden, sources), out.detach(), atol=0, rtol=0)


def test_gradients_are_finite_where_copy_mass_underflows():
    head = CopyHead(d_model=4, radius=0, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    with torch.no_grad():
        head.score_proj.bias.copy_(torch.tensor([200.0, 0.0]))  # all weight on the copy: the readout underflows
    logits = torch.randn(3, V, F_, requires_grad=True)
    out = head(logits, torch.zeros(3, 4), torch.randint(0, MASK, (3, 1)))
    out.logsumexp(dim=1).sum().backward()
    assert torch.isfinite(logits.grad).all() and torch.isfinite(head.score_proj.weight.grad).all()


def test_sources_are_row_major_offsets_with_unknown_outside_the_frame():
    head = CopyHead(d_model=4, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    prev = torch.arange(16).view(1, 1, 4, 4)
    src = head.sources(prev)  # (1, 1, 16, 9)
    assert src.shape == (1, 1, 16, 9)
    assert src[0, 0, 5].tolist() == [0, 1, 2, 4, 5, 6, 8, 9, 10]  # position (1, 1): its 3x3 neighbourhood
    assert src[0, 0, 0].tolist() == [MASK] * 4 + [0, 1, MASK, 4, 5]  # (0, 0): the top-left corner
    x = torch.arange(2 * 3 * 16).view(2, 3, 4, 4)
    before = previous_frames(x, MASK)
    assert (before[:, 0] == MASK).all() and torch.equal(before[:, 1:], x[:, :2])
    assert torch.equal(previous_frames(x, MASK, x[:, 2])[:, 0], x[:, 2])


@pytest.mark.parametrize("dy, dx", [(0, 0), (0, 1), (1, -1)])
def test_a_pointer_fixed_on_one_offset_generates_the_shifted_previous_frame(dy, dx):
    """All score on neighbour (dy, dx): each generated frame copies the previous one shifted by that offset; where
    the neighbour lies outside the frame the readout decides. Cached and uncached generation agree."""
    model = tiny_copy_model(radius=1)
    k = (dy + 1) * 3 + (dx + 1)
    with torch.no_grad():
        model.copy_head.score_proj.weight.zero_()
        model.copy_head.score_proj.bias.fill_(-50.0)
        model.copy_head.score_proj.bias[k] = 50.0
    prompt = torch.randint(0, MASK, (2, 2, 4, 4), generator=torch.Generator().manual_seed(1))
    out, _ = generate_frames(model, prompt, 3, maskgit_steps=2)
    ref, _ = generate_uncached(model, prompt, 3, maskgit_steps=2)
    assert torch.equal(out, ref)
    for t in range(2, 5):
        for y in range(4):
            for x in range(4):
                if 0 <= y + dy < 4 and 0 <= x + dx < 4:
                    assert out[0, t, y, x] == out[0, t - 1, y + dy, x + dx]


@pytest.mark.parametrize("match", [False, True])
@pytest.mark.parametrize("maskgit_steps", [1, 2, 3])
def test_cached_inference_equals_recomputation_with_a_copy_head(maskgit_steps, match):
    model = tiny_copy_model(radius=1, match=match)
    x = torch.randint(0, MASK, (2, 6, 4, 4), generator=torch.Generator().manual_seed(2))
    x[:, 3] = x[:, 2].roll(1, dims=2)  # a shifted frame, so copies matter
    for fns in ((teacher_forced, teacher_forced_uncached), (generate_frames, generate_uncached)):
        runs = []
        for fn in fns:
            args = (model, x) if fn in (teacher_forced, teacher_forced_uncached) else (model, x[:, :2], 4)
            runs.append(fn(*args, maskgit_steps=maskgit_steps, temperature=1.0,
                           generator=torch.Generator().manual_seed(3)))
        (cached_samples, cached_logits), (full_samples, full_logits) = runs
        torch.testing.assert_close(cached_logits, full_logits, atol=1e-5, rtol=1e-5)
        assert torch.equal(cached_samples, full_samples)


def test_logits_are_log_probabilities_and_frame_0_uses_the_readout_alone():
    model = tiny_copy_model(radius=2)
    x = torch.randint(0, MASK, (1, 3, 4, 4))
    with torch.no_grad():
        logp = model.logits(x)
        plain = model.predict_frames(x, greedy=False).readout_logits  # (B, V, F, T, H, W)
    torch.testing.assert_close(logp.exp().sum(dim=1), torch.ones(1, F_, 3, 4, 4))
    frame0 = logp[0, :, :, 0].permute(2, 3, 0, 1).reshape(16, V, F_)  # (S, V, F)
    plain0 = plain[0, :, :, 0].permute(2, 3, 0, 1).reshape(16, V, F_)
    torch.testing.assert_close(frame0, plain0.log_softmax(dim=1), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(logp[0, :, :, 1].exp().amax(dim=0), frame0.exp().amax(dim=1).T.reshape(F_, 4, 4))


def test_config_validation_and_checkpoint_round_trip(tmp_path):
    for bad in (-1, 4, 7):
        with pytest.raises(ConfigError, match="copy_radius"):
            GenieConfig(S=16, image_vocab_size=V ** F_, num_layers=1, d_model=16, num_heads=2, copy_radius=bad)
    assert "copy_head.score_proj.weight" not in STMaskGIT(GenieConfig(num_layers=1)).state_dict()  # published
    model = tiny_copy_model(radius=2)
    assert model.copy_head.score_proj.weight.shape == (26, 32)
    model.save_pretrained(tmp_path / "ckpt")
    assert json.loads((tmp_path / "ckpt" / "config.json").read_text())["copy_radius"] == 2
    loaded = STMaskGIT.from_pretrained(tmp_path / "ckpt")
    x = torch.randint(0, MASK, (1, 4, 4, 4))
    with torch.no_grad():
        torch.testing.assert_close(loaded.logits(x), model.logits(x))


def test_gradients_match_the_dense_mixture_with_repeated_and_dropped_neighbours():
    torch.manual_seed(1)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    N = 6
    sources = torch.randint(0, 4, (N, 9)) * 17  # few distinct values: many repeats, in both factors
    sources[0, :3] = MASK
    sources[1, 5] = 0  # value 0 held by a neighbour while dropped ones also point at it
    sources[1, 6] = MASK
    grads = []
    for fn in (head, lambda *a: dense_copy_mixture(head, *a)):
        logits = (torch.randn(N, V, F_, generator=torch.Generator().manual_seed(2)) * 2).requires_grad_()
        hidden = torch.randn(N, 8, generator=torch.Generator().manual_seed(3)).requires_grad_()
        head.zero_grad()
        out = fn(logits, hidden, sources)
        weights = torch.rand(out.shape, generator=torch.Generator().manual_seed(4))
        (out * weights).sum().backward()
        grads.append((out.detach(), logits.grad, hidden.grad, head.score_proj.weight.grad.clone()))
    for fast, slow in zip(*grads):
        torch.testing.assert_close(fast, slow, atol=1e-5, rtol=1e-4)


def test_match_input_marks_the_neighbours_holding_the_same_token():
    head = CopyHead(d_model=4, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK,
                    match_input=True)
    frames = torch.randint(0, 1000, (1, 3, 4, 4))
    frames[0, 1] = frames[0, 0].roll(1, dims=1)  # frame 1 = frame 0 shifted one column right
    frames[0, 2, 0, 0] = MASK
    sources = head.sources(previous_frames(frames, MASK))
    match = (sources == frames.flatten(2).unsqueeze(-1)) & (frames.flatten(2).unsqueeze(-1) != MASK)
    assert not match[0, 0].any()  # frame 0: no previous frame
    holds = match[0, 1, :, 3].view(4, 4)  # offset (0, -1) holds every token of frame 1 but the first column's
    assert holds[:, 1:].all() and not holds[:, 0].any()
    with torch.no_grad():
        head.match_proj.weight.copy_(torch.arange(9.0).expand(4, 9))  # channel value = sum of matched offsets
        emb = head.match_embedding(frames, sources)
    torch.testing.assert_close(emb[..., 0], (match.float() * torch.arange(9.0)).sum(-1))
    assert emb[0, 2, 0].abs().sum() == 0  # a masked token gets no match
    with pytest.raises(ConfigError, match="copy_match_input"):
        GenieConfig(num_layers=1, copy_match_input=True)


def test_copy_bias_scales_the_copy_weights_and_is_a_decoding_setting(tmp_path):
    torch.manual_seed(3)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    logits, hidden = torch.randn(4, V, F_), torch.randn(4, 8)
    sources = torch.randint(0, MASK, (4, 9))
    sources[0, 2:] = MASK
    with torch.no_grad():
        plain = head(logits, hidden, sources)
        head.copy_bias = 1.5  # the same as raising every neighbour's score bias by 1.5
        biased = head(logits, hidden, sources)
        head.copy_bias = 0.0
        head.score_proj.bias[:-1] += 1.5
        torch.testing.assert_close(head(logits, hidden, sources), biased)
        head.score_proj.bias[:-1] -= 1.5
        head.copy_bias = 60.0  # the new-token option vanishes: only the neighbours' values keep mass
        copies = head(logits, hidden, sources).exp()
    assert not torch.equal(plain, biased)
    factors = factorize_token_ids(sources[0, :2], F_, V)  # (2, F)
    for f in range(F_):
        assert copies[0, factors[:, f], f].sum() == pytest.approx(1.0, abs=1e-5)

    model = tiny_copy_model()
    x = torch.randint(0, MASK, (1, 3, 4, 4))
    with torch.no_grad():
        before = model.logits(x)
        model.set_decoding(model.decoding.override(copy_bias=2.0))
        assert not torch.equal(model.logits(x), before)
        model.save_pretrained(tmp_path / "ckpt")
        loaded = STMaskGIT.from_pretrained(tmp_path / "ckpt")  # saved with the checkpoint, not in the weights
        assert loaded.copy_head.copy_bias == 2.0 and loaded.decoding == model.decoding
        assert set(safetensors.torch.load_file(tmp_path / "ckpt" / "model.safetensors")) == set(model.state_dict())
        model.set_decoding(model.decoding.override(copy_bias=0.0))
        torch.testing.assert_close(model.logits(x), before, atol=0, rtol=0)
    plain_model = STMaskGIT(GenieConfig(num_layers=1))
    plain_model.set_decoding(plain_model.decoding.override(copy_bias=0.0))
    with pytest.raises(ValueError, match="copy head"):
        plain_model.set_decoding(plain_model.decoding.override(copy_bias=1.0))



def joint_mixture_probs(head, logits, hidden, sources):
    """The mixture's probability of every whole token (N, V^F), written out over the whole vocabulary."""
    offered = sources != MASK
    w = head.log_weights(hidden, offered).exp()  # (N, K + 1)
    readout = logits.float().log_softmax(dim=1)  # (N, V, F)
    ids = torch.arange(V ** F_)
    factors = factorize_token_ids(ids, F_, V)  # (V^F, F)
    p = w[:, -1:] * sum(readout[:, factors[:, f], f] for f in range(F_)).exp()
    for k in range(sources.shape[1]):
        p = p + w[:, k:k + 1] * ((ids[None] == sources[:, k:k + 1]) & offered[:, k:k + 1])
    return p


@pytest.mark.parametrize("copy_bias", [0.0, 1.0])
def test_mode_is_the_most_probable_whole_token_of_the_mixture(copy_bias):
    torch.manual_seed(5)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    head.copy_bias = copy_bias
    N, K = 400, 9
    logits, hidden = torch.randn(N, V, F_) * 2, torch.randn(N, 8) * 2
    # neighbours drawn from a few tokens sharing factors, so that the factor-wise argmax can mix two of them
    pool = torch.tensor([[3, 7], [3, 9], [5, 9], [5, 7], [11, 2]])
    sources = (pool[:, 0] + V * pool[:, 1])[torch.randint(0, len(pool), (N, K))]
    sources[:40, :5] = MASK  # some not offered
    sources[40:50] = MASK  # none offered: the readout's own mode
    with torch.no_grad():
        ids, probs = head.mode(logits, hidden, sources)
        joint = joint_mixture_probs(head, logits, hidden, sources)
        factor_wise = unfactorize_token_ids(head(logits, hidden, sources).argmax(dim=1), F_, V)
    torch.testing.assert_close(probs, joint.max(dim=1).values)
    torch.testing.assert_close(joint.gather(1, ids[:, None])[:, 0], probs)
    torch.testing.assert_close(ids[40:50], unfactorize_token_ids(logits[40:50].argmax(dim=1), F_, V), atol=0, rtol=0)
    chimeras = joint.gather(1, factor_wise[:, None])[:, 0] < probs - 1e-6
    assert chimeras.any()  # the factor-wise argmax misses the mode somewhere, and the mode is never worse
    assert (joint.gather(1, factor_wise[:, None])[:, 0] <= probs + 1e-6).all()


def test_best_neighbour_copies_take_the_single_most_weighted_neighbour():
    torch.manual_seed(6)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    N, K = 400, 9
    logits, hidden = torch.randn(N, V, F_) * 2, torch.randn(N, 8) * 2
    # a few tokens repeated over the neighbours: their summed weight often beats the single heaviest neighbour's
    sources = torch.tensor([3, 70, 200, 4000])[torch.randint(0, 4, (N, K))]
    sources[:40, :5] = MASK  # some not offered
    sources[40:50] = MASK  # none offered: the readout's own mode
    with torch.no_grad():
        joint_ids, _ = head.mode(logits, hidden, sources)
        head.best_neighbour_copies = True
        ids, probs = head.mode(logits, hidden, sources)
        joint = joint_mixture_probs(head, logits, hidden, sources)
        weights = head.log_weights(hidden, sources != MASK)[:, :K]
    readout_mode = unfactorize_token_ids(logits.argmax(dim=1), F_, V)
    neighbour_probs = joint.gather(1, sources.clamp(max=MASK - 1)).masked_fill(sources == MASK, -1.0)
    copies = neighbour_probs.max(dim=1).values > joint.gather(1, readout_mode[:, None])[:, 0]
    heaviest = sources.gather(1, weights.argmax(dim=1, keepdim=True))[:, 0]
    # the joint mode's choice between a copy and the readout's token; a copy is the heaviest neighbour's token
    torch.testing.assert_close(ids, torch.where(copies, heaviest, readout_mode), atol=0, rtol=0)
    torch.testing.assert_close(probs, joint.gather(1, ids[:, None])[:, 0])  # the mixture's probability of it
    assert copies.any() and (~copies).any() and not copies[40:50].any()
    assert (ids != joint_ids).any()


def test_greedy_token_choices_are_checked():
    model = tiny_copy_model()
    with pytest.raises(ConfigError, match="greedy_tokens must be one of"):
        model.set_decoding(model.decoding.override(greedy_tokens="nearest"))
    with pytest.raises(ConfigError, match="greedy_tokens must be one of"):
        model.set_decoding(model.decoding.override(greedy_tokens="factored"))  # removed: each factor's argmax
    assert next(iter(GREEDY_TOKEN_CHOICES)) == "joint"
    model.set_decoding(model.decoding.override(greedy_tokens="best_neighbour"))
    assert model.copy_head.best_neighbour_copies
    model.set_decoding(model.decoding.override(greedy_tokens="joint"))
    assert not model.copy_head.best_neighbour_copies


def test_greedy_decoding_takes_the_joint_mode():
    model = tiny_copy_model(radius=1, seed=4, match=True)

    def gen():
        return torch.Generator().manual_seed(0)

    x = torch.randint(0, MASK // 8, (4, 6, 4, 4))
    x[:, 1:] = x[:, :1].roll(1, dims=-1)  # a moving view: neighbours hold the previous frame's tokens
    window = x[:, :3].clone()
    window[:, 2] = MASK
    with torch.no_grad():
        prediction = frame_slice(model.predict_frames(window), 2)  # logits (B, V, F, H, W), mode (B, H, W)
        mode, factor_wise = prediction.mode_ids, unfactorize_token_ids(prediction.logits.argmax(dim=1).movedim(1, -1),
                                                                       F_, V)
        assert not torch.equal(mode, factor_wise)
        # one MaskGIT step decodes the first new frame from the prompt alone: the joint mode, not each factor's argmax
        torch.testing.assert_close(generate_frames(model, x[:, :2], 1, maskgit_steps=1)[0][:, 2], mode, atol=0, rtol=0)
        joint, joint_tf = generate_frames(model, x[:, :2], 3, generator=gen())[0], teacher_forced(model, x, generator=gen())[0]
        torch.testing.assert_close(joint_tf, teacher_forced_uncached(model, x, generator=gen())[0], atol=0, rtol=0)
        torch.testing.assert_close(joint, generate_uncached(model, x[:, :2], 3, generator=gen())[0], atol=0, rtol=0)
        # sampling at a temperature does not read the greedy setting
        drawn = generate_frames(model, x[:, :2], 2, temperature=1.0, generator=gen())[0]
        model.set_decoding(model.decoding.override(greedy_tokens="best_neighbour"))
        torch.testing.assert_close(generate_frames(model, x[:, :2], 2, temperature=1.0, generator=gen())[0], drawn, atol=0,
                                   rtol=0)


def test_best_neighbour_rollouts_agree_cached_and_uncached_and_differ_from_joint():
    model = tiny_copy_model(radius=1, seed=4, match=True)
    with torch.no_grad():  # weights spread over the neighbours (the tiny model's are peaked), copies preferred
        model.copy_head.score_proj.weight.mul_(0.05)
    model.set_decoding(model.decoding.override(copy_bias=3.0))
    torch.manual_seed(1)
    # a few tokens repeated over the frames, so that the neighbours' summed weights and the heaviest one disagree
    x = torch.tensor([5, 300, 1000, 2500])[torch.randint(0, 4, (4, 6, 4, 4))]

    def rollouts():
        with torch.no_grad():
            return (generate_frames(model, x[:, :2], 3, generator=torch.Generator().manual_seed(0))[0],
                    generate_uncached(model, x[:, :2], 3, generator=torch.Generator().manual_seed(0))[0])

    joint, _ = rollouts()
    model.set_decoding(model.decoding.override(greedy_tokens="best_neighbour"))
    best, best_uncached = rollouts()
    torch.testing.assert_close(best, best_uncached, atol=0, rtol=0)
    torch.testing.assert_close(best[:, :2], x[:, :2], atol=0, rtol=0)
    assert not torch.equal(best, joint)


def test_sampling_draws_whole_tokens():
    model = tiny_copy_model(radius=1, seed=4, match=True)

    def gen():
        return torch.Generator().manual_seed(0)

    x = torch.randint(0, MASK // 8, (4, 6, 4, 4))
    x[:, 1:] = x[:, :1].roll(1, dims=-1)
    model.set_decoding(model.decoding.override(copy_bias=30.0))  # no weight left on a new token: every whole-token draw is a neighbour's token
    joint = generate_frames(model, x[:, :2], 1, maskgit_steps=1, temperature=1.0, generator=gen())[0][:, 2]
    torch.testing.assert_close(joint, generate_uncached(model, x[:, :2], 1, maskgit_steps=1, temperature=1.0,
                                                        generator=gen())[0][:, 2], atol=0, rtol=0)
    sources = model.copy_head.sources(x[:, 1:2])[:, 0]  # (B, S, K): frame 2's neighbours in frame 1
    assert (sources == joint.flatten(1).unsqueeze(-1)).any(-1).all()


@pytest.mark.parametrize("temperature", [1.0, 0.5])
def test_whole_token_draws_follow_the_mixture(temperature):
    torch.manual_seed(6)
    head = CopyHead(d_model=8, radius=1, num_factored_vocabs=F_, factored_vocab_size=V, mask_token_id=MASK)
    # one position repeated: two tokens sharing no factor held by several neighbours, one neighbour not offered
    a, b = 3 + V * 7, 5 + V * 9
    sources = torch.tensor([a, a, b, a, b, b, a, MASK, b]).expand(20000, -1)
    logits = (torch.randn(1, V, F_) * 2).expand(20000, -1, -1)
    hidden = torch.randn(1, 8).expand(20000, -1)
    with torch.no_grad():
        log_weights = head.log_weights(hidden, sources != MASK)
        ids, probs = sample_mixture_tokens(log_weights, sources, logits, temperature, torch.Generator().manual_seed(1))
        exact = joint_mixture_probs(head, logits[:1], hidden[:1], sources[:1])[0]
    torch.testing.assert_close(probs, exact[ids])  # the returned confidence: the untempered mixture probability
    counts = torch.bincount(ids, minlength=V ** F_).float() / len(ids)
    if temperature == 1.0:  # an exact draw from the mixture over whole tokens
        assert (counts - exact).abs().max() < 0.015
    else:  # the option from the tempered weights: a neighbour's token with their summed tempered weight
        tempered = (log_weights[0] / temperature).softmax(-1)
        for token in (a, b):
            expected = tempered[:-1][sources[0] == token].sum() + tempered[-1] * logits[0].softmax(0)[
                factorize_token_ids(torch.tensor(token), F_, V), torch.arange(F_)].prod()
            assert abs(counts[token] - expected) < 0.015


def test_a_sampler_gets_the_mixture_and_its_parts_without_the_mode():
    model = tiny_copy_model(radius=1, seed=7, match=True)
    x = torch.randint(0, MASK, (2, 3, 4, 4), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        full = model.predict_frames(x)
        lean = model.predict_frames(x, greedy=False)
    assert full.mode_ids is not None and lean.mode_ids is None and lean.mode_probs is None
    torch.testing.assert_close(lean.logits, full.logits, atol=0, rtol=0)
    for name in ("copy_log_weights", "copy_sources", "readout_logits"):
        torch.testing.assert_close(getattr(lean, name), getattr(full, name), atol=0, rtol=0)


def held_after_stalls(frames_BTHW: torch.Tensor, P: int, ratio: float) -> torch.Tensor:
    """The stall rule written out window by window: every frame after the first generated frame that changes at
    most `ratio` times the prompt's mean share of changed tokens per step repeats that frame."""
    held = frames_BTHW.clone()
    for b in range(len(held)):
        prompt_change = sum((frames_BTHW[b, t] != frames_BTHW[b, t - 1]).float().mean() for t in range(1, P)) / (P - 1)
        for t in range(P, held.shape[1]):
            if (frames_BTHW[b, t] != frames_BTHW[b, t - 1]).float().mean() <= ratio * prompt_change:
                held[b, t + 1:] = frames_BTHW[b, t]
                break
    return held


def test_stalled_rollouts_hold_the_frame_where_they_stopped():
    model = tiny_copy_model(radius=1, seed=4, match=True)
    with torch.no_grad():
        model.copy_head.score_proj.weight.mul_(0.05)
    model.set_decoding(model.decoding.override(copy_bias=3.0))
    model.set_decoding(model.decoding.override(greedy_tokens="best_neighbour"))
    torch.manual_seed(1)
    x = torch.tensor([5, 300, 1000, 2500])[torch.randint(0, 4, (8, 6, 4, 4))]
    x[:4, 1] = x[:4, 0].roll(1, dims=-1)  # prompts that move in different amounts
    P = 2

    def rollout(ratio=None, prompt=P):
        return generate_frames(model, x[:, :prompt], 6 - prompt, generator=torch.Generator().manual_seed(0),
                        stall_ratio=ratio)[0]

    free = rollout()
    prompt_change_B = (x[:, 1] != x[:, 0]).float().mean(dim=(1, 2))
    ratios_Bn = (free[:, P:] != free[:, P - 1:-1]).float().mean(dim=(2, 3)) / prompt_change_B[:, None]
    # a ratio at which some window stalls before its last new frame and another never stalls
    ratio = next(float(v) for v in ratios_Bn.unique() if 0 < v <= 1
                 and (ratios_Bn[:, :-1] <= v).any(1).any() and (ratios_Bn > v).all(1).any())
    held = rollout(ratio)
    torch.testing.assert_close(held, held_after_stalls(free, P, ratio), atol=0, rtol=0)
    assert not torch.equal(held, free)
    torch.testing.assert_close(rollout(1.0), held_after_stalls(free, P, 1.0), atol=0, rtol=0)
    with pytest.raises(ValueError, match="stall_ratio must be in"):
        rollout(0.0)
    with pytest.raises(ValueError, match="at least 2 prompt frames"):
        rollout(0.5, prompt=1)
