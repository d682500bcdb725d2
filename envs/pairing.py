"""What pairs the world model with the real sample world: the real world a model's starts were recorded in."""
from pathlib import Path
from typing import Optional

import numpy as np

from sample_world.render import raw_frames_path


def real_world_for(env, data_dir: Optional[str]):
    """(DoomEnv, raw npz) of the sample world that data_dir was built from, or (None, reason) when there is none: a
    model not driven by buttons, data not from the sample world, or no ViZDoom."""
    if data_dir is None or not env.buttons:
        return None, "the model is not driven by buttons" if data_dir else "no --data_dir"
    data_dir = Path(data_dir)
    raw_npz = raw_frames_path(data_dir)
    if not raw_npz.is_file():
        return None, f"{raw_npz} not found (the data is not a sample world)"
    try:
        from envs.doom import DoomEnv, world_config
    except ImportError as e:
        return None, f"cannot import the real world ({e})"
    cfg = world_config(raw_npz.parent)
    with np.load(raw_npz) as npz:
        maps = sorted(set(str(m) for m in npz["maps"]))
    return DoomEnv(maps=maps, cfg=cfg), raw_npz
