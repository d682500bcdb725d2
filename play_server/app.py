"""play.py's server: one player's world model environment (and the real sample world beside it), and the FastAPI
application of the page and its HTTP API (play.py's doc describes the API)."""
import io
import json
import logging
import threading
import time
from pathlib import Path
from typing import List, Optional, Union

import numpy as np
from PIL import Image

from common.errors import InputError

PAGE = Path(__file__).resolve().parent / "static" / "play.html"
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
        self.real_frame, self.info = None, {}
        self.step_seconds = []

    @property
    def buttons(self) -> Optional[List[str]]:
        return self.env.button_names if self.env.buttons else None

    def state(self) -> dict:
        return {"buttons": self.buttons, "latent_actions": self.env.model.config.num_latent_actions,
                "real_world": self.real_env is not None, "step": self.info.get("step", 0),
                "window": self.info.get("window"), "windows": len(self.env.starts) if self.env.starts else 0,
                "steps_per_second": self.steps_per_second(), "decoding": self.env.model.decoding.to_dict()}

    def steps_per_second(self) -> Optional[float]:
        recent = self.step_seconds[-20:]
        return round(len(recent) / sum(recent), 2) if recent else None

    def reset(self, seed: Optional[int] = None, window: Optional[int] = None) -> np.ndarray:
        with self.lock:
            options = {} if window is None else {"window": window}
            frame, self.info = self.env.reset(seed=seed, options=options)
            self.step_seconds = []
            if self.real_env is not None and self.info["window"] is not None:
                from envs.doom import recorded_start

                start = recorded_start(self.raw_npz, self.env.window_start_frame(self.info["window"]))
                self.real_frame, _ = self.real_env.reset(options=start)
            return frame

    def step(self, action: Union[List[str], int]) -> np.ndarray:
        with self.lock:
            t0 = time.perf_counter()
            if self.env.buttons:  # else a latent action id, or a row of a model's other real action streams
                from envs.doom import buttons_from_names

                action = buttons_from_names(action, self.env.button_names)
            frame, _, _, _, self.info = self.env.step(action)
            if self.real_env is not None:
                self.real_frame, *_ = self.real_env.step(action)
            self.step_seconds.append(time.perf_counter() - t0)
            return frame

    def close(self) -> None:
        """Close the real world's engine (a process of its own); again is a no-op. Waits a little for a step in
        flight, then closes anyway: the server is going away."""
        locked = self.lock.acquire(timeout=10)
        try:
            if self.real_env is not None:
                self.real_env.close()
        finally:
            if locked:
                self.lock.release()


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


def make_session(checkpoint_dir, data_dir: Optional[str] = None, tokenizer_ckpt: Optional[str] = None,
                 device: str = "cpu", decoding=None, prompt_frames: Optional[int] = None, real_world: bool = True,
                 seed: int = 0) -> PlaySession:
    """A session of the model in checkpoint_dir (decoding as its checkpoint says, with the values of `decoding`, a
    dict of genie.decoding.DecodingConfig fields, instead where given), starting from data_dir's windows, with the
    real sample world beside it when `real_world` and there is one; reset to its first start (drawn with `seed`)."""
    from envs.pairing import real_world_for
    from envs.world_model import WorldModelEnv

    env = WorldModelEnv.from_checkpoint(checkpoint_dir, data_dir, tokenizer_ckpt, device=device,
                                        prompt_frames=prompt_frames)
    env.model.set_decoding(env.model.decoding.override(**(decoding or {})))
    real_env, raw_npz = real_world_for(env, data_dir) if real_world else (None, "--no_real_world")
    if real_env is None:
        logger.info("no real world beside the model: %s", raw_npz)
    logger.info("decoding: %s", env.model.decoding.to_dict())
    session = PlaySession(env, real_env, raw_npz if real_env is not None else None)
    session.reset(seed=seed)
    return session
