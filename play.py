#!/usr/bin/env python
"""Play a trained world model live in a browser.

    python play.py --checkpoint_dir data/genie_model/final_checkpt            # then open the URL it prints
    python play.py --checkpoint_dir data/genie_model/final_checkpt --data_dir data/unseen/val   # maps never trained on

The page shows the frame the model imagines, upscaled; hold the arrow keys or W A S D (E: use) or the on-screen
buttons to walk, press R for another start. A latent-action model takes keys 1-8 instead. When the model was trained
on the sample world, the real world plays beside it: the same buttons in ViZDoom, from the same start.

The page talks to the server through the HTTP API that scripts may use as well (one player at a time):
    POST /reset  JSON body optional: {"seed": n} (a start drawn with that seed) or {"window": i} (window i of the
                 data) -> the first frame, image/png
    POST /step   {"action": ["TURN_LEFT"]} (the held buttons, names as in the dataset's buttons stream; a latent
                 action id for a latent-action model) -> the next frame, image/png
    GET  /real.png   the real world's frame after the same actions (404 without a real world)
    GET  /state      JSON: buttons, latent actions, real world or not, step, start window
Bad input (an unknown button, a malformed body) gets HTTP 400 and a one-line reason; the server goes on serving.
"""
import argparse
import io
import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import List, Optional, Union

import numpy as np
from PIL import Image

from common.cli import add_device_arg, add_num_threads_arg, apply_cpu_settings, finite_float, resolve_device, run_main
from common.errors import InputError

PAGE = Path(__file__).resolve().parent / "genie" / "static" / "play.html"
logger = logging.getLogger("play")


def png_bytes(frame_HW3: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(frame_HW3).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


class BadBody(InputError):
    """A request body the API cannot take."""


class PlaySession:
    """One player's world model environment and, when there is one, the real world beside it, driven together.

    Thread-safe: the web server calls it from its worker threads, one call at a time."""

    def __init__(self, env, real_env=None, raw_npz=None):
        self.env, self.real_env, self.raw_npz = env, real_env, raw_npz
        self.lock = threading.Lock()
        self.frame, self.real_frame, self.info = None, None, {}
        self.step_seconds = []

    @property
    def buttons(self) -> Optional[List[str]]:
        return getattr(self.env, "button_names", None) if self.env.buttons else None

    def state(self) -> dict:
        return {"buttons": self.buttons, "latent_actions": self.env.model.config.num_latent_actions,
                "real_world": self.real_env is not None, "step": self.info.get("step", 0),
                "window": self.info.get("window"), "windows": len(self.env.starts) if self.env.starts else 0,
                "steps_per_second": self.steps_per_second()}

    def steps_per_second(self) -> Optional[float]:
        recent = self.step_seconds[-20:]
        return round(len(recent) / sum(recent), 2) if recent else None

    def reset(self, seed: Optional[int] = None, window: Optional[int] = None) -> np.ndarray:
        with self.lock:
            options = {} if window is None else {"window": window}
            self.frame, self.info = self.env.reset(seed=seed, options=options)
            self.step_seconds = []
            if self.real_env is not None and self.info["window"] is not None:
                from data.doom_env import recorded_start

                start = recorded_start(self.raw_npz, self.env.window_start_frame(self.info["window"]))
                self.real_frame, _ = self.real_env.reset(options=start)
            return self.frame

    def step(self, action: Union[List[str], int]) -> np.ndarray:
        with self.lock:
            t0 = time.perf_counter()
            if self.env.buttons:
                from data.doom_env import buttons_from_names

                if not isinstance(action, list):
                    raise InputError(f"action must be a list of held buttons {self.buttons}, got {action!r}")
                model_action = real_action = buttons_from_names(action, self.env.button_names)
            else:  # a latent action id, or a row of a model's other real action streams
                model_action = real_action = action
            self.frame, _, _, _, self.info = self.env.step(model_action)
            if self.real_env is not None:
                self.real_frame, *_ = self.real_env.step(real_action)
            self.step_seconds.append(time.perf_counter() - t0)
            return self.frame


def build_app(session: PlaySession):
    """The FastAPI application of a session: the page and the HTTP API (module doc)."""
    from fastapi import FastAPI, Request
    from fastapi.responses import HTMLResponse, JSONResponse, Response
    from pydantic import BaseModel, ConfigDict, StrictFloat, StrictInt, StrictStr, ValidationError
    from starlette.concurrency import run_in_threadpool

    class ResetRequest(BaseModel):
        model_config = ConfigDict(extra="forbid")
        seed: Optional[StrictInt] = None
        window: Optional[StrictInt] = None

    class StepRequest(BaseModel):
        model_config = ConfigDict(extra="forbid")
        action: Union[StrictInt, List[StrictStr], List[Union[StrictInt, StrictFloat]]]

    app = FastAPI(title="play a world model", docs_url=None, redoc_url=None)

    def bad_request(reason: str) -> JSONResponse:
        return JSONResponse({"error": reason}, status_code=400)

    async def parse(request: Request, schema, empty_ok: bool):
        """The request's JSON body as `schema`, whatever its content type; raises BadBody with a one-line reason."""
        raw = await request.body()
        if not raw.strip() and empty_ok:
            return schema()
        try:
            body = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise BadBody(f"malformed JSON body: {e}") from None
        try:
            return schema.model_validate(body)
        except ValidationError as e:
            error = e.errors()[0]
            where = ".".join(str(p) for p in error["loc"][:1]) or "body"
            raise BadBody(f"{where}: {error['msg']} (got {json.dumps(body)[:80]})") from None

    @app.exception_handler(BadBody)
    async def bad_body(request: Request, exc: BadBody):
        return bad_request(str(exc))

    @app.exception_handler(InputError)
    async def input_error(request: Request, exc: InputError):
        return bad_request(str(exc).splitlines()[0])

    def png(frame: np.ndarray) -> Response:
        return Response(png_bytes(frame), media_type="image/png",
                        headers={"X-Step": str(session.info.get("step", 0)),
                                 "X-Window": str(session.info.get("window"))})

    @app.get("/", response_class=HTMLResponse)
    def page():
        return PAGE.read_text()

    @app.get("/state")
    def state():
        return session.state()

    @app.post("/reset")
    async def reset(request: Request):
        body = await parse(request, ResetRequest, empty_ok=True)
        if body.seed is not None and body.window is not None:
            return bad_request("give seed or window, not both")
        return png(await run_in_threadpool(session.reset, body.seed, body.window))

    @app.post("/step")
    async def step(request: Request):
        body = await parse(request, StepRequest, empty_ok=False)
        return png(await run_in_threadpool(session.step, body.action))

    @app.get("/real.png")
    def real():
        if session.real_frame is None:
            return JSONResponse({"error": "no real world beside this model"}, status_code=404)
        return Response(png_bytes(session.real_frame), media_type="image/png")

    return app


def real_world_for(env, data_dir: Optional[str]):
    """(DoomEnv, raw npz) of the sample world that data_dir was built from, or (None, reason) when there is none: a
    model not driven by buttons, data not from the sample world, or no ViZDoom."""
    if data_dir is None or not env.buttons:
        return None, "the model is not driven by buttons" if data_dir else "no --data_dir"
    data_dir = Path(data_dir)
    raw_npz = data_dir.parent / "raw" / f"{data_dir.name}.npz"
    if not raw_npz.is_file():
        return None, f"{raw_npz} not found (the data is not a sample world)"
    try:
        from data.doom_env import DoomEnv, world_config
    except ImportError as e:
        return None, f"cannot import the real world ({e})"
    cfg = world_config(raw_npz.parent)
    with np.load(raw_npz) as npz:
        maps = sorted(set(str(m) for m in npz["maps"]))
    return DoomEnv(maps=maps, cfg=cfg), raw_npz


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="play.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt",
                   help="dynamics checkpoint directory (config.json + model.safetensors) or hub id (default: "
                        "%(default)s, what ./run_sample.sh trains)")
    p.add_argument("--data_dir", default="data/sample/val",
                   help="token dataset whose windows are the starts (default: %(default)s, held-out walks; "
                        "data/unseen/val: maps never trained on); a sample world's split also gives the real world")
    p.add_argument("--tokenizer_ckpt", default=None,
                   help="tokenizer that decodes the frames (default: the one the data's metadata names)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default: %(default)s, this machine only)")
    p.add_argument("--port", type=int, default=8000, help="port to serve on (default: %(default)s)")
    p.add_argument("--temperature", type=finite_float, default=1.0,
                   help="sampling temperature of each new frame, >= 0; 0 is greedy (default: %(default)s: the "
                        "sampled futures, which beat greedy ones on every set)")
    p.add_argument("--maskgit_steps", type=int, default=2, help="MaskGIT steps per frame, >= 1 (default: %(default)s)")
    p.add_argument("--copy_bias", type=finite_float, default=2.0,
                   help="models with a copy head: added to each previous-frame neighbour's score (default: "
                        "%(default)s, the main command's)")
    p.add_argument("--prompt_frames", type=int, default=None,
                   help="recorded frames of a window given as the start (default: the model's num_prompt_frames)")
    p.add_argument("--no_real_world", action="store_true", help="do not play the real world beside the model")
    p.add_argument("--seed", type=int, default=0, help="seed of the first start and of the sampler")
    add_device_arg(p)
    add_num_threads_arg(p)
    args = p.parse_args(argv)
    if args.temperature < 0 or args.maskgit_steps < 1:
        p.error(f"need --temperature >= 0 and --maskgit_steps >= 1, got {args.temperature}, {args.maskgit_steps}")
    if not 0 < args.port < 65536:
        p.error(f"--port must be in 1..65535, got {args.port}")
    return args


def make_session(args) -> PlaySession:
    from genie.world_env import WorldModelEnv

    device = resolve_device(args.device)
    env = WorldModelEnv.from_checkpoint(args.checkpoint_dir, args.data_dir, args.tokenizer_ckpt, device=device,
                                        copy_bias=args.copy_bias, temperature=args.temperature,
                                        maskgit_steps=args.maskgit_steps, prompt_frames=args.prompt_frames)
    real_env, raw_npz = (None, "--no_real_world") if args.no_real_world else real_world_for(env, args.data_dir)
    if real_env is None:
        logger.info("no real world beside the model: %s", raw_npz)
    session = PlaySession(env, real_env, raw_npz if real_env is not None else None)
    session.reset(seed=args.seed)
    return session


def main(argv=None) -> int:
    import uvicorn

    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    apply_cpu_settings(args.num_threads)
    session = make_session(args)
    app = build_app(session)
    print(f"play: open http://{args.host}:{args.port}/ in a browser (Ctrl-C stops)", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0


if __name__ == "__main__":
    sys.exit(run_main("play.py", main))
