#!/usr/bin/env python
"""Play a trained world model live in a browser.

    python play.py --checkpoint_dir data/genie_model/final_checkpt            # then open the URL it prints
    python play.py --checkpoint_dir data/genie_model/final_checkpt --data_dir data/unseen/val   # maps never trained on

The page shows the frame the model imagines, upscaled; hold the arrow keys or W A S D (E: use) or the on-screen
buttons to walk, press R for another start. A latent-action model takes keys 1-8 instead. When the model was trained
on the sample world, the real world plays beside it: the same buttons in ViZDoom, from the same start. Frames are
sampled as the checkpoint's decoding.json says (the main command's: whole tokens at temperature 1, copy bias 2);
the decoding flags override single values.

The page talks to the server through the HTTP API that scripts may use as well (one player at a time):
    POST /reset  JSON body optional: {"seed": n} (a start drawn with that seed) or {"window": i} (window i of the
                 data) -> the first frame, image/png
    POST /step   {"action": ["TURN_LEFT"]} (the held buttons, names as in the dataset's buttons stream; a latent
                 action id for a latent-action model) -> the next frame, image/png
    GET  /real.png   the real world's frame after the same actions (404 without a real world)
    GET  /state      JSON: buttons, latent actions, real world or not, step, start window, the decoding used
Bad input (an unknown button, a malformed body) gets HTTP 400 and a one-line reason; the server goes on serving.
"""
import argparse
import logging
import sys

from common.cli import add_device_arg, add_num_threads_arg, apply_cpu_settings, resolve_device, run_main
from common.shutdown import exit_on_sigterm
from evaluation.cli import add_decoding_args, check_decoding_args, decoding_overrides


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
    p.add_argument("--prompt_frames", type=int, default=None,
                   help="recorded frames of a window given as the start (default: the model's num_prompt_frames)")
    p.add_argument("--no_real_world", action="store_true", help="do not play the real world beside the model")
    p.add_argument("--seed", type=int, default=0, help="seed of the first start and of the sampler")
    add_device_arg(p)
    add_num_threads_arg(p)
    add_decoding_args(p)
    args = p.parse_args(argv)
    check_decoding_args(p, args)
    if not 0 < args.port < 65536:
        p.error(f"--port must be in 1..65535, got {args.port}")
    return args


def main(argv=None) -> int:
    import uvicorn

    from play_server.app import build_app, make_session

    args = parse_args(argv)
    exit_on_sigterm()  # SIGTERM exits as Ctrl-C does, closing the real world's engine (common/shutdown.py)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    apply_cpu_settings(args.num_threads)
    overrides = decoding_overrides(args)
    session = make_session(args.checkpoint_dir, args.data_dir, args.tokenizer_ckpt, resolve_device(args.device),
                           overrides, args.prompt_frames, not args.no_real_world, args.seed)
    try:
        app = build_app(session)
        print(f"play: open http://{args.host}:{args.port}/ in a browser (Ctrl-C stops)", flush=True)
        uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    finally:  # Ctrl-C, SIGTERM (uvicorn stops serving, then re-raises it: exit_on_sigterm's exit) or an error
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(run_main("play.py", main))
