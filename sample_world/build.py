"""Build the embedded sample world: first-person frames + actions from ViZDoom, tokenized into the 1X layout.

    python -m sample_world.build --output_dir data/sample

1. `sample_world.render` renders train/val episodes (held-out episodes and maps for val) into output_dir/raw/*.npz;
2. the small MAGVIT2 tokenizer shipped in magvit2/pretrained/sample_world_64 (or one trained here with
   --train_tokenizer, using exactly the recipe that produced the shipped weights) encodes 64x64 frames to 16x16 tokens;
3. the tokens, segment ids and actions are written to output_dir/train and output_dir/val (1X layout, with actions/).
Each step is skipped when its output already exists and matches, so a second run is cheap.
The script lives in magvit2/ because it tokenizes: data/ renders the frames and never imports the tokenizer.
"""
import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

from common.cli import (add_device_arg, add_hidden_alias, add_num_threads_arg, apply_cpu_settings, finite_float,
                        non_negative_int, positive_int, resolve_device, run_main)
from common.errors import TrainingError
from common.shutdown import exit_on_sigterm
from sample_world.render import MAP_NAMES_HELP, TRAIN_MAPS, VAL_MAPS, WorldConfig, build_sample_world, map_name
from magvit2.model import VQModel
from magvit2.tokenize_frames import describe_inputs, tokenize_episodes

REPO_ROOT = Path(__file__).resolve().parents[1]
SHIPPED_TOKENIZER = "magvit2/pretrained/sample_world_64"
TOKENIZER_CONFIG = "magvit2/configs/sample_world_64.json"
# The recipe of the shipped tokenizer (see magvit2/pretrained/sample_world_64/README.md): L1 + LPIPS on every second
# step for 1,500 steps of 16 frames; the run went on into its GAN phase (from step 1,500), which made it worse.
TOKENIZER_RECIPE = ["--vq_config", TOKENIZER_CONFIG, "--resolution", "64", "--batch_size", "16",
                    "--learning_rate", "1e-3", "--max_train_steps", "1500", "--perceptual_every", "2", "--augment",
                    "--max_eval_frames", "256", "--eval_every_n_steps", "500", "--use_gan", "--disc_start", "1500",
                    "--mixed_precision", "bf16", "--channels_last", "--num_threads", "1", "--seed", "0"]


def train_tokenizer(raw_dir: Path, output_dir: Path, extra_args=()) -> Path:
    """Train the sample world's tokenizer with magvit2/train.py; returns its final checkpoint directory."""
    final = output_dir / "final_checkpt"
    if (final / "model.safetensors").exists():
        print(f"{final}: tokenizer already trained; reusing it")
        return final
    cmd = [sys.executable, "-m", "magvit2.train", "--train_data", str(raw_dir / "train.npz"),
           "--val_data", str(raw_dir / "val.npz"), "--output_dir", str(output_dir), *TOKENIZER_RECIPE, *extra_args]
    print("training the sample-world tokenizer:", " ".join(cmd))
    code = subprocess.run(cmd).returncode
    if code != 0:
        raise TrainingError(f"training the tokenizer failed (magvit2.train exit status {code}; its message is above)")
    return final


def resolve_tokenizer(path: str) -> Path:
    p = Path(path)
    if not p.exists() and not p.is_absolute() and (REPO_ROOT / p).exists():
        p = REPO_ROOT / p
    if not (p / "model.safetensors").exists():
        raise FileNotFoundError(f"tokenizer checkpoint {path} not found (expected config.json + model.safetensors); "
                                f"train one with `python -m sample_world.build --train_tokenizer`")
    return p


def split_stamp(raw_npzs: list, tokenizer_dir: Path) -> dict:
    """What a token dataset was built from: the raw frames (path, mtime; the files after the first, in order, under
    "more_raw") and the tokenizer weights (content hash, so a fresh checkout of the same weights is recognised while
    new weights are not)."""
    digest = hashlib.sha256((tokenizer_dir / "model.safetensors").read_bytes()).hexdigest()
    first, *more = raw_npzs
    stamp = {"raw": str(first), "raw_mtime": first.stat().st_mtime, "tokenizer_sha256": digest}
    if more:
        stamp["more_raw"] = [[str(p), p.stat().st_mtime] for p in more]
    return stamp


def tokenize_split(raw_npzs: list, out_dir: Path, tokenizer_dir: Path, tokenizer_ref: str, batch_size: int,
                   device, overwrite: bool) -> None:
    """Encode one split's npz files (in order, as one dataset) into a token dataset, unless an up-to-date one is
    already there."""
    stamp = split_stamp(raw_npzs, tokenizer_dir)
    stamp_path = out_dir / "build_stamp.json"
    if not overwrite and stamp_path.exists() and json.loads(stamp_path.read_text()) == stamp:
        print(f"{out_dir}: token dataset up to date; skipping")
        return
    model = VQModel.from_checkpoint(tokenizer_dir).to(device).eval()
    t0 = time.time()
    tokenize_episodes(model, describe_inputs(raw_npzs), out_dir, tokenizer_ckpt=tokenizer_ref,
                      batch_size=batch_size, overwrite=True)
    stamp_path.write_text(json.dumps(stamp, indent=2))
    print(f"{out_dir}: tokenized in {time.time() - t0:.1f}s")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output_dir", default="data/sample", help="root of the sample world (raw/, train/, val/)")
    add_hidden_alias(p, "--out_dir", "output_dir")  # the spelling before train.py's was adopted
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the episode generator")
    p.add_argument("--train_episodes", type=positive_int, default=2,
                   help="episodes per training map (16 maps by default); validation gets 1 held-out episode on each "
                        "of --val_maps")
    p.add_argument("--train_maps", nargs="+", type=map_name, default=list(TRAIN_MAPS),
                   help=f"maps for training: {MAP_NAMES_HELP}")
    p.add_argument("--val_maps", nargs="+", type=map_name, default=list(VAL_MAPS),
                   help="maps of the held-out validation episodes (default: the first 8 training maps and MAP18, "
                        "which is never trained on)")
    p.add_argument("--episode_len", type=positive_int, default=1500, help="frames (35 Hz tics) per episode")
    p.add_argument("--train_episode_len", type=int, default=None,
                   help="frames per training episode, if not --episode_len; the validation split keeps "
                        "--episode_len (e.g. 48 maps x 1 walk of 1000 frames, about the default's training frames, "
                        "with the default's validation split byte for byte)")
    p.add_argument("--turn_speed", type=finite_float, default=WorldConfig.turn_speed,
                   help="degrees the walker turns per tic while a turn button is held (default %(default)s: 13 "
                        "degrees per 15-tic window step; 1.75 was the default before, 26 degrees); lower makes a "
                        "world whose view moves less per step")
    p.add_argument("--tokenizer_ckpt", default=SHIPPED_TOKENIZER,
                   help="tokenizer checkpoint directory used to encode the frames (default: the shipped one)")
    add_hidden_alias(p, "--tokenizer", "tokenizer_ckpt")
    p.add_argument("--train_tokenizer", action="store_true",
                   help="train the tokenizer here with the shipped recipe (into OUTPUT_DIR/tokenizer) instead of "
                        "using the shipped weights")
    p.add_argument("--workers", type=int, default=2,
                   help="processes rendering episodes in parallel (each runs one ViZDoom engine; the frames do not "
                        "depend on it)")
    p.add_argument("--batch_size", type=positive_int, default=8,
                   help="frames per encoder batch when tokenizing (small batches stay in the CPU's caches: 8 encodes "
                        "the 64x64 frames 1.5x faster than 256 on 2 cores, with the same tokens)")
    add_device_arg(p)
    add_num_threads_arg(p)
    p.add_argument("--overwrite", action="store_true", help="rebuild every step even if outputs exist")
    args = p.parse_args(argv)
    if not args.turn_speed > 0:
        p.error(f"--turn_speed must be > 0, got {args.turn_speed}")
    if args.workers < 1:
        p.error(f"--workers must be >= 1, got {args.workers}")
    if args.train_episode_len is not None and args.train_episode_len < 1:
        p.error(f"--train_episode_len must be >= 1, got {args.train_episode_len}")
    return args


def main(argv=None):
    args = parse_args(argv)
    exit_on_sigterm()  # SIGTERM stops the renderer's workers and closes their engines, as Ctrl-C does
    apply_cpu_settings(args.num_threads)
    out = Path(args.output_dir)
    raw = out / "raw"
    build_sample_world(raw, seed=args.seed, train_maps=args.train_maps, val_maps=args.val_maps,
                       train_episodes=args.train_episodes, val_episodes=1, episode_len=args.episode_len,
                       train_episode_len=args.train_episode_len,
                       workers=args.workers, overwrite=args.overwrite,
                       cfg=WorldConfig(turn_speed=args.turn_speed))
    if args.train_tokenizer:
        tokenizer_dir = train_tokenizer(raw, out / "tokenizer")
        tokenizer_ref = str(tokenizer_dir)
    else:
        tokenizer_dir = resolve_tokenizer(args.tokenizer_ckpt)
        tokenizer_ref = args.tokenizer_ckpt
    for split in ("train", "val"):
        tokenize_split([raw / f"{split}.npz"], out / split, tokenizer_dir, tokenizer_ref, args.batch_size,
                       resolve_device(args.device), args.overwrite)


if __name__ == "__main__":
    sys.exit(run_main("sample_world.build", main))
