"""The play protocol: what a player sees, scored against the real world's pixels over a minute of play.

From starts spread over the recorded walks of a sample-world split, the world model environment (envs/world_model.py,
what `play.py` serves) gets P real frames as its prompt and then replays the walk's own buttons for K steps (15 tics
each; 64 steps are 27 s), its context running over its own frames as a player's session does. Each step's frame is
scored against the real frame the walk recorded at that moment, not against the tokenizer's decoding of it:

- PSNR and LPIPS (AlexNet) to the real frame, for the model, for holding the last real prompt frame (the baseline a
  model must beat) and for the tokenizer's own reconstruction of the real frame (the ceiling of any model that
  speaks in its tokens);
- sharpness: the mean absolute Laplacian of the grey image, as a share of the real frame's (a blurred or dissolving
  world drops below 1);
- per horizon bin (steps 1-8, 9-16, 17-32, 33-64): the means of the above and KID x 1000, the kernel distance
  between the set of frames and the set of real frames of the bin (unbiased, cubic polynomial kernel, on the
  spatially pooled LPIPS AlexNet features: offline and fixed), which sees a world that drifts off the real one's
  look even where no single frame can be matched.

The token dataset must sit in a sample world's layout, `<root>/<split>` beside `<root>/raw/<split>.npz` with the
same frames (build.sh writes both). `evaluate.py --protocol play` is its command line; with --figures_dir it also
draws the curves (play_curves.png) and one drive side by side (play_drive.gif: model | tokenizer | real).
"""
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch
from tqdm import tqdm

from common.images import kid, psnr, sharpness
from data import RawTokenDataset, TokenDatasetError, read_metadata
from evaluation.metrics import images_to_unit_range
from evaluation.protocols import EvaluationError, apply_decoding, load_real_frames, start_process
from magvit2.lpips import LPIPS
from sample_world.render import STEP_TICS, raw_frames_path

logger = logging.getLogger("evaluation.play_protocol")

HORIZON_BINS = ((1, 8), (9, 16), (17, 32), (33, 64), (65, 128), (129, 256))
WORLDS = ("model", "tokenizer", "hold")  # what is scored against the real frames
FEATURE_CHUNK = 64


@dataclass
class PlayConfig:
    """A play run: `starts_per_episode` starts spread over each recorded walk of data_dir, prompted with
    prompt_frames real frames (None: the model's num_prompt_frames), then `steps` steps of the walk's buttons.
    decoding: overrides of the checkpoint's decoding (DecodingConfig fields). figures_dir: where the plot and the GIF
    go (None: nowhere)."""
    data_dir: str = "data/sample/val"
    checkpoint_dir: str = "data/genie_model/final_checkpt"
    steps: int = 64
    starts_per_episode: int = 2
    prompt_frames: Optional[int] = None
    tokenizer_ckpt: Optional[str] = None
    decoding: Dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    figures_dir: Optional[str] = None
    device: str = "auto"
    num_threads: int = 0


# ------------------------------------------------------------------ scores
def horizon_bins(steps: int) -> List[tuple]:
    """The bins of HORIZON_BINS that start within `steps`, the last one cut at `steps`."""
    return [(lo, min(hi, steps)) for lo, hi in HORIZON_BINS if lo <= steps]


class PlayScorer:
    """Per-frame scores against real frames, and the pooled features KID compares."""

    def __init__(self, device: torch.device):
        self.lpips = LPIPS().to(device)
        self.device = device

    def frame_scores(self, images_NHW3: torch.Tensor, real_NHW3: torch.Tensor) -> dict:
        """{"psnr", "lpips", "sharpness"} (N,) of uint8 images against the real ones (same shape)."""
        images, real = images_NHW3.to(self.device), real_NHW3.to(self.device)
        with torch.no_grad():
            lpips = torch.cat([self.lpips(images_to_unit_range(images[a:a + FEATURE_CHUNK]),
                                          images_to_unit_range(real[a:a + FEATURE_CHUNK]))
                               for a in range(0, len(images), FEATURE_CHUNK)])
        return {"psnr": psnr(images.float(), real.float(), value_range=(0.0, 255.0)).cpu(), "lpips": lpips.cpu(),
                "sharpness": sharpness(images).cpu()}

    def features(self, images_NHW3: torch.Tensor) -> torch.Tensor:
        images = images_NHW3.to(self.device)
        return torch.cat([self.lpips.pooled_features(images_to_unit_range(images[a:a + FEATURE_CHUNK]))
                          for a in range(0, len(images), FEATURE_CHUNK)]).cpu()


def summarize(scores: Dict[str, Dict[str, np.ndarray]], features: Dict[str, torch.Tensor], steps: int) -> dict:
    """scores: world ("model", "tokenizer", "hold", "real") -> metric -> (starts, steps); features: world ->
    (starts, steps, d). Returns per step (means over starts) and per horizon bin: each world's PSNR, LPIPS, sharpness
    as a share of the real frames' (ratio of the means) and KID x 1000 to the real frames of the bin."""
    real_sharp = scores["real"]["sharpness"]
    per_step, per_bin = {}, []
    for world in WORLDS:
        s = scores[world]
        per_step[world] = {"psnr": s["psnr"].mean(0).tolist(), "lpips": s["lpips"].mean(0).tolist(),
                           "sharpness": (s["sharpness"].mean(0) / real_sharp.mean(0)).tolist()}
    for lo, hi in horizon_bins(steps):
        cut = slice(lo - 1, hi)
        row = {"bin": f"{lo}-{hi}", "steps": [lo, hi]}
        real_feats = features["real"][:, cut].flatten(0, 1)
        for world in WORLDS:
            s = scores[world]
            row[world] = {"psnr": float(s["psnr"][:, cut].mean()), "lpips": float(s["lpips"][:, cut].mean()),
                          "sharpness": float(s["sharpness"][:, cut].mean() / real_sharp[:, cut].mean()),
                          "kid_x1000": 1000 * kid(features[world][:, cut].flatten(0, 1), real_feats)}
        per_bin.append(row)
    return {"per_step": per_step, "per_bin": per_bin}


# ------------------------------------------------------------------ starts and drives
def real_frames_for(data_dir, num_images: int) -> np.ndarray:
    """The real frames of a sample world split (`raw_frames_path`); a clear error when they are not there."""
    raw_npz = raw_frames_path(data_dir)
    if not raw_npz.is_file():
        raise EvaluationError(f"the play protocol scores against the real frames, but {raw_npz} (the raw frames of "
                              f"{data_dir}) was not found: the data must be a sample world split (build.sh)")
    return load_real_frames(raw_npz, num_images)


def play_starts(dataset: RawTokenDataset, per_episode: int) -> List[int]:
    """Indices of dataset windows (each P + K frames at stride 15), `per_episode` evenly spread over each walk (its
    first and last possible start included when there are two or more)."""
    starts = np.asarray(dataset.valid_start_inds)
    segments = (np.asarray(dataset.segment_ids)[starts] if dataset.segment_ids is not None
                else np.zeros(len(starts), dtype=np.int64))
    chosen = []
    for segment in np.unique(segments):
        inds = np.flatnonzero(segments == segment)
        picks = np.linspace(0, len(inds) - 1, per_episode).round().astype(int) if per_episode > 1 else [0]
        chosen.extend(int(inds[i]) for i in sorted(set(picks)))
    return chosen


def drive(env, item: dict, prompt_frames: int, steps: int, seed: int) -> np.ndarray:
    """Prompt `env` (WorldModelEnv) with the first prompt_frames token frames of a dataset window and replay the
    window's action rows for `steps` steps. Returns the frames the model shows, (steps, H, W, 3) uint8."""
    config = env.model.config
    tokens = item["tokens"][:prompt_frames].numpy()
    rows = (np.concatenate([item["actions"][n].numpy() for n in config.action_names], axis=-1)
            if config.action_dim else None)
    options = {"tokens": tokens}
    if rows is not None and prompt_frames > 1:
        options["actions"] = rows[:prompt_frames - 1]
    env.reset(seed=seed, options=options)
    frames = []
    for k in range(steps):
        if rows is None:
            frame, *_ = env.step(0)
        else:
            frame, *_ = env.step_row(rows[prompt_frames - 1 + k])
        frames.append(frame)
    return np.stack(frames)


# ------------------------------------------------------------------ figures
def plot_curves(result: dict, path: Path) -> None:
    """PSNR, LPIPS and sharpness per step for each world, and KID per bin, as one PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"model": "tab:red", "tokenizer": "tab:green", "hold": "tab:grey"}
    fig, axes = plt.subplots(1, 4, figsize=(18, 4))
    steps = np.arange(1, result["steps"] + 1)
    for ax, metric, label in zip(axes, ("psnr", "lpips", "sharpness"),
                                 ("PSNR to the real frame (dB)", "LPIPS to the real frame", "sharpness / real's")):
        for world in WORLDS:
            ax.plot(steps, result["per_step"][world][metric], label=world, color=colours[world])
        ax.set_xlabel("step of play (15 tics)")
        ax.set_title(label)
    bins = [row["bin"] for row in result["per_bin"]]
    x = np.arange(len(bins))
    for i, world in enumerate(WORLDS):
        axes[3].bar(x + (i - 1) * 0.27, [row[world]["kid_x1000"] for row in result["per_bin"]], width=0.27,
                    label=world, color=colours[world])
    axes[3].set_xticks(x, bins)
    axes[3].set_xlabel("steps")
    axes[3].set_title("KID x 1000 to the real frames")
    axes[0].legend()
    fig.suptitle(f"{result['data_dir']}: {result['num_starts']} starts, {result['steps']} steps")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def save_drive_gif(model_KHW3: np.ndarray, tokenizer_KHW3: np.ndarray, real_KHW3: np.ndarray, path: Path,
                   scale: int = 3, fps: float = 35 / STEP_TICS) -> None:
    """One drive side by side, model | tokenizer's reconstruction | real, `scale` x nearest, at play speed."""
    from PIL import Image

    frames = []
    for row in zip(model_KHW3, tokenizer_KHW3, real_KHW3):
        strip = np.concatenate([np.pad(f, ((2, 2), (2, 2), (0, 0)), constant_values=255) for f in row], axis=1)
        frames.append(Image.fromarray(strip).resize((strip.shape[1] * scale, strip.shape[0] * scale),
                                                    Image.Resampling.NEAREST))
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)


# ------------------------------------------------------------------ the run
def run_play(cfg: PlayConfig) -> dict:
    """The play protocol's JSON line (module doc): data_dir, steps, prompt_frames, num_starts, the decoding,
    per_step and per_bin scores (`summarize`); writes the figures to cfg.figures_dir when set."""
    from envs.world_model import WorldModelEnv

    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    # the tokenizer that made the tokens decodes them: the dataset's, unless --tokenizer_ckpt says otherwise
    tokenizer_ckpt = cfg.tokenizer_ckpt or read_metadata(Path(cfg.data_dir)).get("tokenizer_ckpt")
    env = WorldModelEnv.from_checkpoint(cfg.checkpoint_dir, None, tokenizer_ckpt=tokenizer_ckpt, device=str(device))
    config = env.model.config
    if config.num_latent_actions:
        raise EvaluationError("the play protocol replays the recorded buttons; a latent-action model is driven by "
                              "latent ids, which a recorded walk does not have")
    apply_decoding(env.model, cfg.decoding, cfg.checkpoint_dir)
    P = int(cfg.prompt_frames or config.num_prompt_frames or 1)
    if not 1 <= P <= config.T - 1:
        raise EvaluationError(f"--num_prompt_frames must be in 1..{config.T - 1} for this model, got {P}")
    try:
        dataset = RawTokenDataset(cfg.data_dir, window_size=P + cfg.steps, stride=STEP_TICS)
    except TokenDatasetError as e:
        raise EvaluationError(f"{e}\n(the play protocol needs {P} prompt frames and --play_steps {cfg.steps} at "
                              f"stride {STEP_TICS}: use fewer --play_steps)") from None
    if len(dataset) == 0:
        raise EvaluationError(f"{cfg.data_dir}: no walk holds {P} prompt frames and {cfg.steps} steps at stride "
                              f"{STEP_TICS} ({(P + cfg.steps - 1) * STEP_TICS + 1} frames); use fewer --play_steps")
    if config.action_dim:
        from training.action_streams import prepare_action_streams
        prepare_action_streams(config, dataset)
    real = real_frames_for(cfg.data_dir, dataset.metadata["num_images"])
    tokenizer = env.tokenizer
    starts = play_starts(dataset, cfg.starts_per_episode)
    logger.info("play: %d starts of %s, %d prompt frames, %d steps", len(starts), cfg.data_dir, P, cfg.steps)

    scorer = PlayScorer(device)
    scores = {w: {m: [] for m in ("psnr", "lpips", "sharpness")} for w in WORLDS}
    scores["real"] = {"sharpness": []}
    features = {w: [] for w in WORLDS + ("real",)}
    first_drive = None
    for i, window in enumerate(tqdm(starts, desc="play", unit="start")):
        item = dataset[window]
        first = int(dataset.valid_start_inds[window])
        frame_inds = first + STEP_TICS * np.arange(P - 1, P + cfg.steps)  # the last prompt frame, then each step
        real_KHW3 = torch.from_numpy(np.ascontiguousarray(real[frame_inds]))
        images = {"model": torch.from_numpy(drive(env, item, P, cfg.steps, cfg.seed + i)),
                  "hold": real_KHW3[:1].expand(cfg.steps, -1, -1, -1),
                  "real": real_KHW3[1:]}
        with torch.no_grad():
            images["tokenizer"] = tokenizer.tokens_to_images(item["tokens"][P:P + cfg.steps].long().to(device)).cpu()
        for world in WORLDS:
            for metric, values in scorer.frame_scores(images[world], images["real"]).items():
                scores[world][metric].append(values.numpy())
        scores["real"]["sharpness"].append(sharpness(images["real"]).numpy())
        for world in WORLDS + ("real",):
            features[world].append(scorer.features(images[world]))
        if first_drive is None:
            first_drive = {w: images[w].numpy() for w in ("model", "tokenizer", "real")}
    stacked = {w: {m: np.stack(v) for m, v in s.items()} for w, s in scores.items()}
    result = {"protocol": "play", "data_dir": str(cfg.data_dir), "checkpoint_dir": str(cfg.checkpoint_dir),
              "steps": cfg.steps, "prompt_frames": P, "num_starts": len(starts),
              "decoding": env.model.decoding.to_dict(),
              **summarize(stacked, {w: torch.stack(f) for w, f in features.items()}, cfg.steps)}
    if cfg.figures_dir is not None:
        out = Path(cfg.figures_dir)
        plot_curves(result, out / "play_curves.png")
        save_drive_gif(first_drive["model"], first_drive["tokenizer"], first_drive["real"], out / "play_drive.gif")
        logger.info("play figures: %s, %s", out / "play_curves.png", out / "play_drive.gif")
    return result


def bin_lines(result: dict) -> List[str]:
    """A readable table of the per-bin scores (for logs)."""
    lines = [f"{'steps':>7} | " + " | ".join(f"{w:^29}" for w in WORLDS),
             f"{'':>7} | " + " | ".join(f"{'PSNR':>6} {'LPIPS':>6} {'sharp':>6} {'KID':>7}" for _ in WORLDS)]
    for row in result["per_bin"]:
        cells = [f"{row[w]['psnr']:6.2f} {row[w]['lpips']:6.3f} {row[w]['sharpness']:6.2f} {row[w]['kid_x1000']:7.1f}"
                 for w in WORLDS]
        lines.append(f"{row['bin']:>7} | " + " | ".join(cells))
    return lines
