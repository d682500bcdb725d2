"""Playing speed: steps per second through play.py's HTTP API, and the sliding-window step against recomputing the
window.

    python benchmarks/bench_play.py --checkpoint_dir data/genie_model/final_checkpt --data_dir data/unseen/val

1. play.py's server runs in this process (uvicorn on a free local port, the real world beside the model when the
   data is a sample world) and a client posts /reset, then --steps /step requests one after the other, cycling
   through held buttons; each returns the decoded frame as a PNG. Steps per second = steps / wall time, decoding,
   PNG and HTTP included, after --warmup steps.
2. The model's step alone (no decoding), from the same start: genie.inference.next_frame, which computes the
   context's temporal keys/values once per step (and keeps them while the context grows), against
   genie.reference.next_frame_recomputed, which recomputes the whole window at every MaskGIT step (the published
   way), on the same contexts with the same random state: milliseconds per step and the ratio, while the context
   grows and once it slides (T-1 frames), and the share of tokens on which the two agree.
The last line is JSON.
"""
import argparse
import json
import socket
import sys
import threading
import time
import urllib.request

import numpy as np
import torch

from common.cli import add_num_threads_arg, apply_cpu_settings, finite_float, positive_int, run_main

ACTIONS = (["MOVE_FORWARD"], ["TURN_LEFT"], ["MOVE_FORWARD", "TURN_RIGHT"], [], ["TURN_RIGHT"], ["MOVE_BACKWARD"])


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt", help="the model to play")
    p.add_argument("--data_dir", default="data/unseen/val", help="token dataset of the starts")
    p.add_argument("--steps", type=positive_int, default=64, help="timed /step requests (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=8, help="untimed /step requests first (default: %(default)s)")
    p.add_argument("--model_steps", type=positive_int, default=24,
                   help="steps of the cached-vs-recomputed comparison (default: %(default)s)")
    p.add_argument("--temperature", type=finite_float, default=None,
                   help="play.py's --temperature (default: the checkpoint's decoding)")
    p.add_argument("--no_real_world", action="store_true", help="serve without the real world beside the model")
    p.add_argument("--seed", type=int, default=0)
    add_num_threads_arg(p)
    args = p.parse_args(argv)
    if args.warmup < 0:
        p.error(f"--warmup must be >= 0, got {args.warmup}")
    return args


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def post(url: str, body: dict) -> bytes:
    request = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=60) as response:
        return response.read()


def http_steps_per_second(session, args) -> float:
    """Serve the session with uvicorn in a thread and time /step requests from a client in this thread."""
    import uvicorn

    from play_server.app import build_app

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(build_app(session), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        while not server.started:
            time.sleep(0.02)
        base = f"http://127.0.0.1:{port}"
        post(f"{base}/reset", {"window": 0})
        for i in range(args.warmup):
            post(f"{base}/step", {"action": ACTIONS[i % len(ACTIONS)]})
        t0 = time.perf_counter()
        for i in range(args.steps):
            png = post(f"{base}/step", {"action": ACTIONS[i % len(ACTIONS)]})
            assert png[:8] == b"\x89PNG\r\n\x1a\n"
        return args.steps / (time.perf_counter() - t0)
    finally:
        server.should_exit = True
        thread.join(timeout=10)


def model_step_times(env, args) -> dict:
    """ms per step of next_frame (cached) and next_frame_recomputed on the same contexts, growing and sliding."""
    from genie.inference import next_frame
    from genie.reference import next_frame_recomputed

    env.reset(seed=args.seed, options={"window": 0})
    times = {"growing": ([], []), "sliding": ([], [])}
    same = []  # share of the new frame's tokens the two agree on (float rounding can flip a near-tie)
    cache = None
    for i in range(args.model_steps):
        if env.buttons:
            action = np.isin(env.button_names, ACTIONS[i % len(ACTIONS)]).astype(np.int8)
        else:  # a latent action id, or a row of zeros for a model of other action streams
            action = 0 if env.latent or not env.model.config.action_dim else np.zeros(env.model.config.action_dim)
        tokens, actions, latent = env.step_inputs(action)
        if len(tokens) < len(env._tokens):  # the context slid: nothing cached holds it
            cache = None
        phase = "growing" if len(tokens) < env.T - 1 else "sliding"
        state = env._generator.get_state()
        t0 = time.perf_counter()
        decoding = env.model.decoding
        frame, cache = next_frame(env.model, tokens, actions, latent, cache, decoding.maskgit_steps,
                                  decoding.temperature, torch.Generator().set_state(state))
        t1 = time.perf_counter()
        again = next_frame_recomputed(env.model, tokens, actions, latent, decoding.maskgit_steps,
                                      decoding.temperature, torch.Generator().set_state(state))
        t2 = time.perf_counter()
        same.append(float((frame == again).float().mean()))
        times[phase][0].append(t1 - t0)
        times[phase][1].append(t2 - t1)
        env.step(action)  # move the env on (its own cache; not timed)
    out = {}
    for phase, (cached, full) in times.items():
        if cached:
            out[phase] = {"steps": len(cached), "cached_ms": 1000 * float(np.mean(cached)),
                          "recomputed_ms": 1000 * float(np.mean(full)), "speedup": float(np.mean(full) / np.mean(cached))}
    out["same_tokens"] = float(np.mean(same))
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    from play_server.app import make_session

    overrides = {} if args.temperature is None else {"temperature": args.temperature}
    session = make_session(args.checkpoint_dir, args.data_dir, device="cpu", decoding=overrides,
                           real_world=not args.no_real_world, seed=args.seed)
    steps_per_second = http_steps_per_second(session, args)
    real = session.real_env is not None
    print(f"/step through HTTP: {steps_per_second:.1f} steps/s (decoding + PNG + HTTP, real world beside: "
          f"{'yes' if real else 'no'}, temperature {session.env.model.decoding.temperature}, "
          f"{torch.get_num_threads()} threads)")
    model = model_step_times(session.env, args)
    for phase in ("growing", "sliding"):
        if phase in model:
            t = model[phase]
            print(f"model step, context {phase}: cached {t['cached_ms']:.1f} ms, recomputing the window "
                  f"{t['recomputed_ms']:.1f} ms: {t['speedup']:.2f}x ({t['steps']} steps)")
    print(f"the two agree on {100 * model['same_tokens']:.2f} % of the new frames' tokens (same context, actions and "
          f"random state; float rounding can flip a near-tie)")
    print(json.dumps({"http_steps_per_second": steps_per_second, "real_world": real,
                      "temperature": session.env.model.decoding.temperature, "threads": torch.get_num_threads(), "model_step": model}))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("bench_play.py", main))
