"""Playing speed: steps per second in the page in a headless browser and through play.py's HTTP API, and the
model's step with its temporal cache against recomputing the window.

    python benchmarks/bench_play.py --checkpoint_dir data/genie_model/final_checkpt --data_dir data/unseen/val

0. The page as a player sees it: play.py's server runs in this process, Debian's chromium (headless, through
   selenium: pip install -e .[test]) opens the page and holds walking keys for --browser_seconds (a new key every
   second); steps/s = the page's step counter over that time, after --warmup steps, beside the page's own readout
   (its last 20 steps). Skipped with --browser_seconds 0 or without chromium.
1. play.py's server runs in this process (uvicorn on a free local port, the real world beside the model when the
   data is a sample world) and a client posts /reset, then --steps /step requests one after the other, cycling
   through held buttons; each returns the decoded frame as a PNG. Steps per second = steps / wall time, decoding,
   PNG and HTTP included, after --warmup steps.
2. The model's step alone (no decoding), from the same start: the environment's step (genie.inference.next_frame,
   which computes the context's temporal keys/values once per step and keeps them while the context grows; the
   context restarts from its last num_prompt_frames frames when the window is full) against
   genie.reference.next_frame_recomputed, which recomputes the whole window at every MaskGIT step (the published
   way), on the same contexts with the same random state: milliseconds per step and the ratio, on steps whose
   context was cached and on restarts, and the share of tokens on which the two agree; and the mean step against
   sliding a context of the last T-1 frames by one frame a step (next_frame recomputing them every step).
The last line is JSON.
"""
import argparse
import contextlib
import json
import socket
import sys
import threading
import time
import urllib.request
from typing import Optional

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
    p.add_argument("--browser_seconds", type=finite_float, default=20.0,
                   help="seconds of walking in the page in headless chromium (default: %(default)s; 0 skips it)")
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
    if args.browser_seconds < 0:
        p.error(f"--browser_seconds must be >= 0, got {args.browser_seconds}")
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


@contextlib.contextmanager
def serving(session):
    """play.py's server of `session` on a free local port, in a thread; yields its base URL."""
    import uvicorn

    from play_server.app import build_app

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(build_app(session), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        while not server.started:
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)


def page_steps_per_second(session, args) -> Optional[dict]:
    """Walk in the page in headless chromium: {"steps_per_second": counted, "page_readout": the page's own figure},
    or None where there is no browser."""
    from play_server.browser import headless_chromium

    browser, reason = headless_chromium()
    if browser is None:
        print(f"page in a browser: skipped ({reason})")
        return None
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    keys = (Keys.ARROW_UP, Keys.ARROW_LEFT, Keys.ARROW_DOWN, Keys.ARROW_RIGHT)

    def steps() -> int:  # the page's step counter
        return int(browser.find_element(By.ID, "step").text)

    try:
        with serving(session) as base:
            browser.get(base + "/")
            WebDriverWait(browser, 60).until(
                lambda b: (b.find_element(By.ID, "model").get_attribute("src") or "").startswith("blob:"))
            ActionChains(browser).key_down(keys[0]).perform()
            WebDriverWait(browser, 60).until(lambda b: steps() >= args.warmup)
            s0, t0, held, i = steps(), time.perf_counter(), keys[0], 0
            while time.perf_counter() - t0 < args.browser_seconds:
                time.sleep(max(0.0, min(1.0, args.browser_seconds - (time.perf_counter() - t0))))
                i += 1
                ActionChains(browser).key_up(held).key_down(keys[i % len(keys)]).perform()
                held = keys[i % len(keys)]
            s1, t1 = steps(), time.perf_counter()
            readout = browser.find_element(By.ID, "fps").text
            ActionChains(browser).key_up(held).perform()
    finally:
        browser.quit()
    return {"steps_per_second": (s1 - s0) / (t1 - t0), "page_readout": float(readout), "steps": s1 - s0}


def http_steps_per_second(session, args) -> float:
    """Serve the session with uvicorn in a thread and time /step requests from a client in this thread."""
    with serving(session) as base:
        post(f"{base}/reset", {"window": 0})
        for i in range(args.warmup):
            post(f"{base}/step", {"action": ACTIONS[i % len(ACTIONS)]})
        t0 = time.perf_counter()
        for i in range(args.steps):
            png = post(f"{base}/step", {"action": ACTIONS[i % len(ACTIONS)]})
            assert png[:8] == b"\x89PNG\r\n\x1a\n"
        return args.steps / (time.perf_counter() - t0)


def model_step_times(env, args) -> dict:
    """ms per step of the environment's step (next_frame with the temporal cache, the context restarting when the
    window is full), of sliding a context of the last T-1 frames by one frame a step instead (next_frame recomputing
    those T-1 frames every step: the environment before the restart) and of next_frame_recomputed (the whole window
    at every MaskGIT step), on the same contexts; "cached" steps reuse the cache of the step before, "restart" steps
    recompute the context."""
    from genie.inference import next_frame
    from genie.reference import next_frame_recomputed

    env.reset(seed=args.seed, options={"window": 0})
    times = {"cached": ([], []), "restart": ([], [])}
    all_steps, sliding = [], []
    same = []  # share of the new frame's tokens the two agree on (float rounding can flip a near-tie)
    cache = None
    decoding = env.model.decoding
    for i in range(args.model_steps):
        if env.buttons:
            action = np.isin(env.button_names, ACTIONS[i % len(ACTIONS)]).astype(np.int8)
        else:  # a latent action id, or a row of zeros for a model of other action streams
            action = 0 if env.latent or not env.model.config.action_dim else np.zeros(env.model.config.action_dim)
        known = len(env._tokens)
        tokens, actions, latent = env.step_inputs(action)
        # next_frame recomputes a context the cache does not hold (after a restart)
        phase = "cached" if cache is not None and cache.length == len(tokens) else "restart"
        state = env._generator.get_state()
        t0 = time.perf_counter()
        frame, cache = next_frame(env.model, tokens, actions, latent, cache, decoding.maskgit_steps,
                                  decoding.temperature, torch.Generator().set_state(state))
        t1 = time.perf_counter()
        again = next_frame_recomputed(env.model, tokens, actions, latent, decoding.maskgit_steps,
                                      decoding.temperature, torch.Generator().set_state(state))
        t2 = time.perf_counter()
        same.append(float((frame == again).float().mean()))
        times[phase][0].append(t1 - t0)
        times[phase][1].append(t2 - t1)
        all_steps.append(t1 - t0)
        if known >= env.T - 1:  # what sliding would compute here: the last T-1 known frames, none of them cached
            slide = env._inputs_with(env.action_row(action), keep=env.T - 1)
            t3 = time.perf_counter()
            next_frame(env.model, *slide, None, decoding.maskgit_steps, decoding.temperature,
                       torch.Generator().set_state(state))
            sliding.append(time.perf_counter() - t3)
        env.step(action)  # move the env on (its own cache; not timed)
    out = {}
    for phase, (cached, full) in times.items():
        if cached:
            out[phase] = {"steps": len(cached), "cached_ms": 1000 * float(np.mean(cached)),
                          "recomputed_ms": 1000 * float(np.mean(full)), "speedup": float(np.mean(full) / np.mean(cached))}
    out["per_step_ms"] = 1000 * float(np.mean(all_steps))
    if sliding:
        out["sliding_ms"] = 1000 * float(np.mean(sliding))
        out["speedup_over_sliding"] = float(np.mean(sliding) / np.mean(all_steps))
    out["same_tokens"] = float(np.mean(same))
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    apply_cpu_settings(args.num_threads)
    from play_server.app import make_session

    overrides = {} if args.temperature is None else {"temperature": args.temperature}
    session = make_session(args.checkpoint_dir, args.data_dir, device="cpu", decoding=overrides,
                           real_world=not args.no_real_world, seed=args.seed)
    real = session.real_env is not None
    page = page_steps_per_second(session, args) if args.browser_seconds > 0 else None
    if page is not None:
        print(f"the page in headless chromium: {page['steps_per_second']:.1f} steps/s over {page['steps']} steps "
              f"(its own readout at the end: {page['page_readout']:.1f}; real world beside: {'yes' if real else 'no'}, "
              f"{torch.get_num_threads()} threads)")
    steps_per_second = http_steps_per_second(session, args)
    print(f"/step through HTTP: {steps_per_second:.1f} steps/s (decoding + PNG + HTTP, real world beside: "
          f"{'yes' if real else 'no'}, temperature {session.env.model.decoding.temperature}, "
          f"{torch.get_num_threads()} threads)")
    model = model_step_times(session.env, args)
    for phase, what in (("cached", "the context cached from the step before"),
                        ("restart", "the context restarted and recomputed")):
        if phase in model:
            t = model[phase]
            print(f"model step, {what}: {t['cached_ms']:.1f} ms, recomputing the window at every MaskGIT step "
                  f"{t['recomputed_ms']:.1f} ms: {t['speedup']:.2f}x ({t['steps']} steps)")
    if "sliding_ms" in model:
        print(f"model step on average: {model['per_step_ms']:.1f} ms; sliding the last T-1 frames by one frame a step "
              f"instead (recomputed every step): {model['sliding_ms']:.1f} ms: {model['speedup_over_sliding']:.2f}x")
    print(f"the two agree on {100 * model['same_tokens']:.2f} % of the new frames' tokens (same context, actions and "
          f"random state; float rounding can flip a near-tie)")
    print(json.dumps({"page": page, "http_steps_per_second": steps_per_second, "real_world": real,
                      "temperature": session.env.model.decoding.temperature, "threads": torch.get_num_threads(), "model_step": model}))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("bench_play.py", main))
