"""Rank policies inside a world model and check the ranking against the real sample world
(`./evaluate.py --protocol policies`).

The task is getting away from the start: a policy's return is how far from its start (map units, 64 ~ 2 m) it ends
after K window steps. Not the path length: a policy that shuttles forward and back travels far and gets nowhere, and
one that walks into a wall keeps pressing forward and stays put.

Each start is a recorded walk of the explorer on one of the maps (episode seed and frame drawn from --seed): the
real world replays it to the start frame, and its last P frames (15 tics apart) and the buttons held between them
are the world model's prompt. From the same start every policy then drives, for K steps, closed loop:
- the real world (envs/doom.py): `real_return` from the engine's poses (a walk that takes a level's exit or a
  teleporter ends where it stood);
- the world model (envs/world_model.py): the policy sees the model's frames, its buttons drive the model;
  `model_return` is the motion estimator's (sample_world/motion_estimator.py: frames in, motion out, no actions read)
  dead reckoning of the model's frames;
- `real_frames_return`: the same estimator on the real world's frames (what a perfect world model would reach);
- `blind_return`: dead reckoning from the commanded buttons alone, as if there were no walls (no world model).
The rankings of the policies by each estimate are scored against the ranking by `real_return` (evaluation/ranking.py).
A policy's random numbers and the model's sampler get the same seed in both worlds for a start (common random
numbers).
"""
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
from tqdm import tqdm

from common.errors import InputError
from sample_world.render import BUTTON_NAMES, HZ, STEP_TICS, driving_command
from sample_world.motion_estimator import distance_from_start
from sample_world.policies import check_action
from evaluation.ranking import (bootstrap_interval, kendall, mean_maximum_rank_violation, pairwise_accuracy, pearson,
                                regret_at_1, spearman, spearman_p_value)

MAX_START_TRIES = 20


class PolicyEvalError(InputError):
    """Maps, starts or settings the policy protocol cannot use."""


@dataclass
class Start:
    """A start: where the real world begins (`DoomEnv.reset` options) and the world model's prompt."""
    options: dict  # map, episode_seed, frame: the first prompt frame of the recorded walk
    prompt_frames: np.ndarray  # (P, 64, 64, 3) uint8, 15 tics apart; the last is where the policies begin
    prompt_rows: np.ndarray  # (P - 1, 5) the buttons' means over each step between them
    seed: int


def make_starts(real_env, maps: Sequence[str], starts_per_map: int, prompt_frames: int, seed: int,
                latest_frame: int = 900) -> List[Start]:
    """`starts_per_map` starts on each map, drawn from `seed`: a walk seed and a frame of it (one whose walk gets
    there without leaving the map)."""
    starts = []
    for m, map_name in enumerate(maps):
        rng = np.random.default_rng([seed, m])
        for i in range(starts_per_map):
            for _ in range(MAX_START_TRIES):
                options = {"map": map_name, "episode_seed": int(rng.integers(2**32 - 1)),
                           "frame": int(rng.integers(0, latest_frame))}
                try:
                    starts.append(replay_start(real_env, options, prompt_frames, seed * 100_000 + m * 1000 + i))
                    break
                except InputError:  # the walk left the map (an exit) before the start: draw another
                    continue
            else:
                raise PolicyEvalError(f"{map_name}: no walk reached a start in {MAX_START_TRIES} tries")
    return starts


def replay_start(real_env, options: dict, prompt_frames: int, seed: int) -> Start:
    """Put the real world at the start (the recorded walk's frame + (P-1) steps) and collect the prompt."""
    frame, _ = real_env.reset(options=options)
    frames, rows = [frame], []
    for _ in range(prompt_frames - 1):
        rows.append(real_env.follow_explorer(STEP_TICS).mean(axis=0))
        frames.append(real_env.frame)
    return Start(options, np.stack(frames), np.asarray(rows, dtype=np.float32).reshape(-1, len(BUTTON_NAMES)), seed)


class RealWorld:
    """The real sample world behind the interface the protocol drives a world through."""

    def __init__(self, env):
        self.env = env

    def begin(self, start: Start) -> np.ndarray:
        replay_start(self.env, start.options, len(start.prompt_frames), start.seed)
        self.start_pose = self.env.pose
        return self.env.frame

    def step(self, buttons: np.ndarray) -> np.ndarray:
        return self.env.step(buttons)[0]


class ModelWorld:
    """A world model environment (WorldModelEnv) behind the same interface, started from the start's prompt."""

    def __init__(self, env):
        self.env = env

    def begin(self, start: Start) -> np.ndarray:
        frame, _ = self.env.reset(seed=start.seed, options={"frames": start.prompt_frames,
                                                           "actions": start.prompt_rows})
        return frame

    def step(self, buttons: np.ndarray) -> np.ndarray:
        return self.env.step(buttons)[0]


def drive(world, policy, name: str, start: Start, steps: int):
    """Run `policy` for `steps` steps in `world` from `start`: (frames (steps + 1, 64, 64, 3), buttons (steps, 5))."""
    frame = world.begin(start)
    policy.reset(start.seed)
    frames, held = [frame], []
    for _ in range(steps):
        buttons = check_action(policy.act(frame), name)
        frame = world.step(buttons)
        frames.append(frame)
        held.append(buttons)
    return np.stack(frames), np.stack(held)


def blind_steps(held_K5: np.ndarray, cfg) -> np.ndarray:
    """(K, 2) per-step (forward map units, turn degrees) that the held buttons command, walls ignored."""
    linear, angular = (driving_command(held_K5, cfg).astype(np.float64) * STEP_TICS / HZ).T
    return np.stack([linear, np.degrees(angular)], axis=1)


def evaluate_policies(policies: Dict[str, object], real_env, model_world, estimator, starts: List[Start],
                      steps: int, progress: bool = True) -> dict:
    """Every policy from every start in both worlds; the protocol's JSON result (module doc)."""
    real_world = RealWorld(real_env)
    returns = {name: {k: [] for k in ("real", "model", "real_frames", "blind")} for name in policies}
    t0 = time.time()
    bar = tqdm(total=len(policies) * len(starts), desc="policies", unit="episode", disable=not progress)
    for start in starts:
        for name, policy in policies.items():
            real_frames, held = drive(real_world, policy, name, start, steps)
            r = returns[name]
            r["real"].append(float(np.hypot(real_env.pose[0] - real_world.start_pose[0],
                                            real_env.pose[1] - real_world.start_pose[1])))
            r["real_frames"].append(distance_from_start(estimator.motion(real_frames)))
            r["blind"].append(distance_from_start(blind_steps(held, real_env.cfg)))
            model_frames, _ = drive(model_world, policy, name, start, steps)
            r["model"].append(distance_from_start(estimator.motion(model_frames)))
            bar.update(1)
    bar.close()
    return summarize(returns, steps, len(starts), time.time() - t0)


def summarize(returns: Dict[str, Dict[str, list]], steps: int, num_starts: int, seconds: float) -> dict:
    names = list(returns)
    rows = []
    for name in names:
        row = {"name": name}
        for kind in ("real", "model", "real_frames", "blind"):
            values = np.asarray(returns[name][kind])
            row[f"{kind}_return"] = float(values.mean())
            row[f"{kind}_return_std"] = float(values.std())
        rows.append(row)
    truth = [r["real_return"] for r in rows]

    def scores(kind: str) -> list:
        return [r[f"{kind}_return"] for r in rows]

    def per_start(kind: str) -> np.ndarray:  # (starts, policies)
        return np.stack([np.asarray(returns[name][kind], dtype=np.float64) for name in names], axis=1)

    best = max(truth)
    regret = regret_at_1(truth, scores("model"))
    mmrv = mean_maximum_rank_violation(truth, scores("model"))
    real_SN, model_SN, blind_SN = per_start("real"), per_start("model"), per_start("blind")
    return {
        "protocol": "policies", "steps": steps, "num_starts": num_starts, "num_policies": len(names),
        "policies": rows,
        "spearman": spearman(truth, scores("model")), "kendall": kendall(truth, scores("model")),
        "pairwise_accuracy": pairwise_accuracy(truth, scores("model")), "regret_at_1": regret,
        "regret_at_1_share": regret / best if best > 0 else 0.0,
        "pearson": pearson(truth, scores("model")),
        "mmrv": mmrv, "mmrv_share": mmrv / best if best > 0 else 0.0,
        # how sure: starts resampled with replacement (95 %), and rho against orderings unrelated to the truth
        "spearman_ci": bootstrap_interval(spearman, real_SN, model_SN),
        "spearman_minus_blind_ci": bootstrap_interval(lambda t, m, b: spearman(t, m) - spearman(t, b),
                                                      real_SN, model_SN, blind_SN),
        "spearman_p": spearman_p_value(truth, scores("model")),
        "blind_spearman": spearman(truth, scores("blind")),
        "real_frames_spearman": spearman(truth, scores("real_frames")),
        "model_pick": names[int(np.argmax(scores("model")))], "real_best": names[int(np.argmax(truth))],
        "time_s": seconds,
    }


def ranking_lines(result: dict) -> List[str]:
    """Readable lines of a result: one per policy, best real return first, then the metrics."""
    lines = [f"{'policy':<20} {'real':>7} {'model':>7} {'real frames':>11} {'blind':>7}   (map units from the start)"]
    for r in sorted(result["policies"], key=lambda r: -r["real_return"]):
        lines.append(f"{r['name']:<20} {r['real_return']:7.1f} {r['model_return']:7.1f} "
                     f"{r['real_frames_return']:11.1f} {r['blind_return']:7.1f}")
    lines.append(f"spearman {result['spearman']:.3f} (blind {result['blind_spearman']:.3f}, real frames "
                 f"{result['real_frames_spearman']:.3f}), kendall {result['kendall']:.3f}, pairwise accuracy "
                 f"{result['pairwise_accuracy']:.3f}, regret@1 {result['regret_at_1']:.1f} "
                 f"({100 * result['regret_at_1_share']:.1f} % of the best)")
    if "spearman_ci" in result:  # results written before these keys existed lack them
        low, high = result["spearman_ci"]
        d_low, d_high = result["spearman_minus_blind_ci"]
        lines.append(f"pearson {result['pearson']:.3f}, MMRV {result['mmrv']:.1f} ({100 * result['mmrv_share']:.1f} % "
                     f"of the best); spearman 95 % interval over starts [{low:.3f}, {high:.3f}], minus blind "
                     f"[{d_low:+.3f}, {d_high:+.3f}], permutation p {result['spearman_p']:.2g}; "
                     f"{result['num_policies']} policies x {result['num_starts']} starts")
    return lines


# ------------------------------------------------------------------ evaluate.py --protocol policies
DEFAULT_MAPS = ("MAP02", "MAP03", "MAP06", "MAP07")  # the first set of maps no run trains on


@dataclass
class PolicyRankingConfig:
    """The policies protocol's settings: `policies` (built-in names or path/to/file.py:ClassName) from `starts` starts
    on each of `maps`, `steps` window steps each, the starts drawn with `seed`; the model of checkpoint_dir (frames
    decoded by tokenizer_ckpt, default the sample world's) prompted with num_prompt_frames recorded frames (None: the
    model's num_prompt_frames), decoding as its checkpoint says overridden by `decoding` (DecodingConfig fields);
    the cloned policies and the motion estimator kept in policy_dir, trained on first use from policy_train_data."""
    checkpoint_dir: str
    policies: List[str]
    maps: List[str] = field(default_factory=lambda: list(DEFAULT_MAPS))
    starts: int = 4
    steps: int = 16
    seed: int = 0
    num_prompt_frames: Optional[int] = None
    tokenizer_ckpt: Optional[str] = None
    decoding: Dict[str, Any] = field(default_factory=dict)
    policy_dir: str = "data/policies"
    policy_train_data: str = "data/sample/raw/train.npz"
    device: str = "auto"
    num_threads: int = 0


def ensure_trained(cfg: PolicyRankingConfig, device="cpu") -> None:
    """Train the cloned policies (when cfg.policies names one) and the motion estimator into cfg.policy_dir unless
    they are there, recorded as trained from cfg.policy_train_data (and the cloned ones over this version's macro
    actions, the estimator as this version's network): weights of another world, data, set of macro actions or
    network are retrained, with a line saying why."""
    import logging
    from pathlib import Path

    from sample_world.motion_estimator import train_motion_estimator, version_mismatch
    from sample_world.policies import BC_BUDGETS, BC_RECORD, bc_weights, stale_reason, stamp_source, train_bc_policies

    logger = logging.getLogger("evaluate")
    policy_dir, train_npz = Path(cfg.policy_dir), Path(cfg.policy_train_data)
    estimator = policy_dir / "motion_estimator.safetensors"
    wanted_bc = any(p.partition("_random")[0] in BC_BUDGETS for p in cfg.policies if ":" not in p)
    stale_bc = stale_reason(bc_weights(policy_dir), policy_dir / BC_RECORD, train_npz, True) if wanted_bc else None
    stale_estimator = (stale_reason([estimator], estimator.with_suffix(".json"), train_npz, False)
                       or version_mismatch(estimator))
    if (stale_bc or stale_estimator) and not train_npz.is_file():
        raise PolicyEvalError(f"--policy_train_data {train_npz} not found: the recorded walks that the cloned "
                              f"policies and the motion estimator learn from (./build.sh makes them), needed "
                              f"because {stale_bc or stale_estimator}")
    if stale_bc:
        logger.info("training the cloned policies into %s: %s", policy_dir, stale_bc)
        train_bc_policies(train_npz, policy_dir, seed=0)
    if stale_estimator:
        logger.info("training the motion estimator into %s: %s", estimator, stale_estimator)
        train_motion_estimator(train_npz, estimator, seed=0, device=device)
        stamp_source(estimator.with_suffix(".json"), train_npz)


def run_policies(cfg: PolicyRankingConfig) -> dict:
    """evaluate.py --protocol policies: the JSON line (module doc); readable lines to stderr."""
    import logging
    from pathlib import Path

    from envs.doom import DoomEnv, world_config
    from evaluation.protocols import apply_decoding, start_process
    from sample_world.motion_estimator import load_motion_estimator
    from sample_world.policies import load_policies
    from envs.world_model import WorldModelEnv

    logger = logging.getLogger("evaluate")
    device = start_process(cfg.device, cfg.num_threads, cfg.seed)
    maps = list(cfg.maps)
    ensure_trained(cfg, device)
    policies = load_policies(cfg.policies, Path(cfg.policy_dir))
    estimator = load_motion_estimator(Path(cfg.policy_dir) / "motion_estimator.safetensors")
    env = WorldModelEnv.from_checkpoint(cfg.checkpoint_dir, None, cfg.tokenizer_ckpt, device=device)
    apply_decoding(env.model, cfg.decoding, cfg.checkpoint_dir)
    if not env.buttons:
        raise PolicyEvalError(f"--checkpoint_dir {cfg.checkpoint_dir}: the policies protocol drives a model with "
                              f"the sample world's buttons; this one takes {env.model.config.action_names}")
    raw_dir = Path(cfg.policy_train_data).parent
    world = world_config(raw_dir) if (raw_dir / "sample_world.json").is_file() else None
    real_env = DoomEnv(maps=maps, cfg=world)
    try:
        prompt = cfg.num_prompt_frames or env.prompt_frames
        starts = make_starts(real_env, maps, cfg.starts, prompt, cfg.seed)
        result = evaluate_policies(policies, real_env, ModelWorld(env), estimator, starts, cfg.steps)
    finally:
        real_env.close()
    for line in ranking_lines(result):
        logger.info(line)
    return {**result, "maps": maps, "starts_per_map": cfg.starts, "seed": cfg.seed,
            "checkpoint_dir": str(cfg.checkpoint_dir), "num_prompt_frames": prompt, **env.model.decoding.to_dict()}
