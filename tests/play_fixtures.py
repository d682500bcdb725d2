"""Tiny world models, tokenizers and token datasets for the play tests (environments, server, browser)."""
from pathlib import Path

import numpy as np
import torch

from data import write_token_dataset
from genie.config import GenieConfig
from genie.decoding import DecodingConfig
from genie.model import STMaskGIT
from magvit2 import VQConfig, VQModel

# how the main command's model is sampled (recipes/sample_world.json), and so the tiny models too
MAIN_DECODING = DecodingConfig(temperature=1.0, copy_bias=2.0, greedy_tokens="best_neighbour")

T = 4  # a short window: the context restarts after a few steps


def tiny_tokenizer(path: Path) -> Path:
    """A small random 64x64 -> 16x16 tokenizer."""
    torch.manual_seed(0)
    VQModel(VQConfig(base_channels=32, ch_mult=[1, 2, 2], num_res_blocks=1, resolution=64)).save_pretrained(path)
    return path


def tiny_model(path: Path, latent: int = 0, seed: int = 0) -> Path:
    """A random 1-layer dynamics model with a copy head, driven by 5 buttons (or `latent` latent actions), saved with
    the main command's decoding (MAIN_DECODING)."""
    torch.manual_seed(seed)
    actions = ({"num_latent_actions": latent} if latent else
               {"action_names": ["buttons"], "action_dim": 5, "action_step_mean": True})
    config = GenieConfig(num_layers=1, num_heads=2, d_model=32, T=T, S=256, image_vocab_size=262144,
                         num_prompt_frames=2, copy_radius=1, copy_match_input=True, **actions)
    model = STMaskGIT(config)
    model.init_weights()
    with torch.no_grad():  # make the actions matter: a strong action projection
        if model.action_cond is not None and config.action_dim:
            model.action_cond.action_proj.weight.normal_(0, 1.0)
    model.set_decoding(MAIN_DECODING)
    model.save_pretrained(path)
    return path


def tiny_dataset(path: Path, tokenizer: Path, num_frames: int = 200, latent: int = 0) -> Path:
    """Random tokens with random held buttons (and latent ids), in windows of T frames at stride 15."""
    rng = np.random.default_rng(0)
    video = rng.integers(0, 262144, size=(num_frames, 16, 16))
    actions = {"buttons": (rng.random((num_frames, 5)) < 0.3).astype(np.float32)}
    if latent:
        actions["latent_action"] = rng.integers(0, latent, size=(num_frames, 1)).astype(np.float32)
    return write_token_dataset(path, video, np.zeros(num_frames, dtype=np.int32), actions=actions,
                               metadata={"hz": 35, "tokenizer_ckpt": str(tokenizer)})


def tiny_play_world(root: Path) -> dict:
    """A tiny sample world (raw walks of MAP01 + their token dataset), its tokenizer and a tiny model driven by its
    buttons: what play.py needs to serve the model with the real world beside it. Needs vizdoom."""
    from sample_world import render as sw
    from sample_world.build import tokenize_split

    tokenizer = tiny_tokenizer(root / "tokenizer")
    cfg = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60)
    sw.build_sample_world(root / "raw", train_maps=("MAP01",), val_maps=("MAP01",), train_episodes=1,
                          episode_len=120, workers=1, cfg=cfg)
    tokenize_split([root / "raw" / "val.npz"], root / "val", tokenizer, str(tokenizer), 8, "cpu", False)
    return {"root": root, "data": root / "val", "model": tiny_model(root / "model"), "tokenizer": tokenizer}
