"""VQModel: the MAGVIT2 tokenizer (encoder, LFQ, decoder), image <-> token conversion and checkpoint loading.

Checkpoints it reads:
- our directory layout: `config.json` (VQConfig) + `model.safetensors` (written by `save_pretrained`, with a
  MANIFEST.json of their digests that loading verifies);
- a `.safetensors` file holding `encoder.*` / `decoder.*` weights;
- a published Open-MAGVIT2 / PyTorch Lightning `.ckpt` (e.g. the 1X `magvit2.ckpt`, docs/formats.md §4): a torch pickle whose
  `state_dict` holds `encoder.*`, `decoder.*`, `loss.*` (ignored) and EMA copies `model_ema.<name without dots>`.
  It is read with `torch.load(weights_only=True)`; a pickle that needs arbitrary code is refused unless the caller
  explicitly passes `allow_unsafe_pickle=True` (CLI flag `--allow_unsafe_pickle`).
"""
import contextlib
import logging
import os
import pickle
import re
import shutil
import tempfile
from pathlib import Path
from typing import Dict, Optional, Tuple, Union

import numpy as np
import torch
import torch.nn as nn
from einops import rearrange
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from common.config import ConfigError
from common.errors import CheckpointError, writing
from common.files import atomic_file
from common.integrity import update_manifest, verify_manifest
from magvit2.config import VQConfig
from magvit2.lfq import LFQ, LFQOutput, ids_to_latents, latents_to_ids
from magvit2.modules import Decoder, Encoder

logger = logging.getLogger(__name__)

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
EMA_PREFIX = "model_ema."
MAX_LISTED_KEYS = 20

ArrayLike = Union[np.ndarray, torch.Tensor]




class VQModel(nn.Module):
    """MAGVIT2 tokenizer. Images (B, 3, H, W) in [-1, 1] <-> latents (B, z, H/f, W/f) <-> token ids (B, H/f, W/f)."""

    def __init__(self, config: Optional[VQConfig] = None):
        super().__init__()
        self.config = config if config is not None else VQConfig()
        self.encoder = Encoder(self.config)
        self.decoder = Decoder(self.config)
        self.quantizer = LFQ(self.config.z_channels, self.config.entropy_temperature)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def encode(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        """Images (B, in_channels, H, W) in [-1, 1] -> continuous latents (B, z_channels, H/f, W/f)."""
        return self.encoder(x_BCHW)

    def quantize(self, z_BCHW: torch.Tensor, compute_losses: Optional[bool] = None) -> LFQOutput:
        """Continuous latents -> LFQOutput (+-1 latents, token ids, losses when training or asked)."""
        return self.quantizer(z_BCHW, compute_losses)

    def decode(self, zq_BCHW: torch.Tensor) -> torch.Tensor:
        """Quantized latents (B, z_channels, h, w) -> images (B, out_channels, h*f, w*f), roughly in [-1, 1]."""
        return self.decoder(zq_BCHW)

    def forward(self, x_BCHW: torch.Tensor) -> Tuple[torch.Tensor, LFQOutput]:
        """Reconstruct images: returns (x_rec_BCHW, LFQOutput)."""
        quantized = self.quantize(self.encode(x_BCHW))
        return self.decode(quantized.zq), quantized

    def _autocast(self):
        if self.device.type == "cuda":
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    @torch.no_grad()
    def images_to_tokens(self, images_BHWC: ArrayLike, batch_size: int = 32) -> ArrayLike:
        """uint8 images (B, H, W, 3) -> int64 token ids (B, H/f, W/f), in batches on the model's device.

        Returns numpy for numpy input (memmaps are read one batch at a time), else a tensor on the input's device.
        """
        _check_images(images_BHWC, self.config)

        def encode_batch(images: torch.Tensor) -> torch.Tensor:
            x_BCHW = rearrange(images, "B H W C -> B C H W").float() / 127.5 - 1
            with self._autocast():
                return latents_to_ids(self.encoder(x_BCHW))

        return self._map_batches(images_BHWC, batch_size, encode_batch)

    @torch.no_grad()
    def tokens_to_images(self, tokens_BHW: ArrayLike, batch_size: int = 32) -> ArrayLike:
        """Integer token ids (B, h, w) -> uint8 images (B, h*f, w*f, 3) = clamp((x + 1) * 127.5, 0, 255).

        Returns numpy for numpy input (memmaps are read one batch at a time), else a tensor on the input's device.
        """
        _check_tokens(tokens_BHW, self.config)

        def decode_batch(ids_BHW: torch.Tensor) -> torch.Tensor:
            _check_token_range(ids_BHW, self.config)
            with self._autocast():
                x_BCHW = self.decoder(ids_to_latents(ids_BHW.long(), self.config.z_channels))
            return rearrange(((x_BCHW.float() + 1) * 127.5).clamp(0, 255).to(torch.uint8), "B C H W -> B H W C")

        return self._map_batches(tokens_BHW, batch_size, decode_batch)

    def _map_batches(self, array: ArrayLike, batch_size: int, fn) -> ArrayLike:
        """fn over batches moved to the model's device; numpy in -> numpy out, tensor in -> tensor on its device."""
        is_numpy = isinstance(array, np.ndarray)
        outputs = []
        for start in range(0, max(len(array), 1), batch_size):  # an empty input still gives a correctly shaped output
            chunk = array[start:start + batch_size]
            if is_numpy:  # uint32 and other dtypes torch handles poorly become int64 (uint8 images stay uint8)
                chunk = np.asarray(chunk)
                chunk = torch.from_numpy(chunk if chunk.dtype == np.uint8 else chunk.astype(np.int64))
            out = fn(chunk.to(self.device))
            outputs.append(out.cpu().numpy() if is_numpy else out.to(array.device))
        return np.concatenate(outputs) if is_numpy else torch.cat(outputs)

    def save_pretrained(self, save_directory) -> None:
        """Write `config.json` + `model.safetensors`.

        A new directory is written under a temporary name and renamed into place; in an existing directory each file
        is replaced atomically (other files there, e.g. training state, are kept).
        """
        save_directory = Path(save_directory)
        state_dict = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        if save_directory.exists():
            atomic_file(save_directory / CONFIG_NAME, lambda p: self.config.save(p), "the tokenizer config")
            atomic_file(save_directory / WEIGHTS_NAME, lambda p: save_file(state_dict, p, {"format": "pt"}),
                        "the tokenizer weights")
            update_manifest(save_directory, (CONFIG_NAME, WEIGHTS_NAME))
            return
        with writing("the tokenizer checkpoint", save_directory):
            save_directory.parent.mkdir(parents=True, exist_ok=True)
            tmp_dir = Path(tempfile.mkdtemp(prefix=f".{save_directory.name}.", dir=save_directory.parent))
            os.chmod(tmp_dir, 0o755)  # mkdtemp makes it private; the checkpoint is an ordinary directory
            try:
                self.config.save(tmp_dir / CONFIG_NAME)
                save_file(state_dict, tmp_dir / WEIGHTS_NAME, {"format": "pt"})
                update_manifest(tmp_dir)
                os.replace(tmp_dir, save_directory)
            except BaseException:
                shutil.rmtree(tmp_dir, ignore_errors=True)
                raise

    @classmethod
    def from_checkpoint(cls, path, config: Optional[VQConfig] = None, use_ema: bool = True,
                        allow_unsafe_pickle: bool = False, map_location="cpu") -> "VQModel":
        """Load a tokenizer from our directory, a .safetensors file or a published Lightning .ckpt.

        config: the architecture; None reads the directory's config.json, or for weight files infers z_channels,
            base_channels, ch_mult, num_res_blocks, in/out channels from the weight shapes.
        use_ema: for a .ckpt, use the `model_ema.*` weights when the file has them (the 1X decoding does).
        allow_unsafe_pickle: let torch.load run arbitrary code from the pickle. Only for files you trust.
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"tokenizer checkpoint not found: {path}")
        if path.is_dir():
            state_dict, dir_config = _load_directory(path)
            config = config if config is not None else dir_config
        else:
            if path.suffix == ".safetensors":
                state_dict = _load_safetensors(path)
            else:
                state_dict = _select_weights(_load_lightning_state_dict(path, allow_unsafe_pickle), use_ema, path)
            config = config if config is not None else infer_config(state_dict, source=str(path))
        model = cls(config)
        _check_fits(model, state_dict, path)
        model.load_state_dict(state_dict, strict=True)
        return model.to(map_location) if map_location is not None else model

    @classmethod
    def from_pretrained(cls, path, **kwargs) -> "VQModel":
        """Alias of `from_checkpoint` (the Hugging Face name)."""
        return cls.from_checkpoint(path, **kwargs)


def _check_images(images, config: VQConfig) -> None:
    if not isinstance(images, (np.ndarray, torch.Tensor)):
        raise TypeError(f"images must be a numpy array or tensor, got {type(images).__name__}")
    if images.dtype not in (np.uint8, torch.uint8):
        raise TypeError(f"images must be uint8 (B, H, W, {config.in_channels}), got dtype {images.dtype}")
    if images.ndim != 4 or images.shape[-1] != config.in_channels:
        raise ValueError(f"images must have shape (B, H, W, {config.in_channels}), got {tuple(images.shape)}")
    f = config.downsample_factor
    if images.shape[1] % f or images.shape[2] % f:
        raise ValueError(f"image size {images.shape[1]}x{images.shape[2]} is not divisible by the tokenizer's "
                         f"downsample factor {f}")


def _check_tokens(tokens, config: VQConfig) -> None:
    if not isinstance(tokens, (np.ndarray, torch.Tensor)):
        raise TypeError(f"tokens must be a numpy array or tensor, got {type(tokens).__name__}")
    is_int = (np.issubdtype(tokens.dtype, np.integer) if isinstance(tokens, np.ndarray)
              else not (tokens.dtype.is_floating_point or tokens.dtype.is_complex or tokens.dtype == torch.bool))
    if not is_int:
        raise TypeError(f"tokens must be integers, got dtype {tokens.dtype}")
    if tokens.ndim != 3:
        raise ValueError(f"tokens must have shape (B, h, w), got {tuple(tokens.shape)}")


def _check_token_range(ids: torch.Tensor, config: VQConfig) -> None:
    if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= config.codebook_size):
        raise ValueError(f"token ids must be in [0, {config.codebook_size}) for z_channels={config.z_channels}, "
                         f"got values in [{int(ids.min())}, {int(ids.max())}]")


def _load_directory(path: Path) -> Tuple[Dict[str, torch.Tensor], VQConfig]:
    missing = [name for name in (CONFIG_NAME, WEIGHTS_NAME) if not (path / name).is_file()]
    if missing:
        raise FileNotFoundError(f"tokenizer directory {path} lacks {', '.join(missing)} (expected {CONFIG_NAME} + "
                                f"{WEIGHTS_NAME}, as written by VQModel.save_pretrained)")
    verify_manifest(path, [WEIGHTS_NAME])  # IntegrityError (a CheckpointError) naming corrupt weights
    return _load_safetensors(path / WEIGHTS_NAME), VQConfig.from_pretrained(path / CONFIG_NAME)


def _load_safetensors(path: Path) -> Dict[str, torch.Tensor]:
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as e:
        raise CheckpointError(f"{path}: not a readable safetensors file ({e})") from None


def _load_lightning_state_dict(path: Path, allow_unsafe_pickle: bool) -> Dict[str, torch.Tensor]:
    """torch.load a Lightning checkpoint (weights_only unless explicitly allowed) and return its state_dict."""
    try:
        obj = torch.load(path, map_location="cpu", weights_only=not allow_unsafe_pickle)
    except pickle.UnpicklingError as e:
        detail = _unpickler_detail(str(e))
        if "global" in detail.lower():
            raise CheckpointError(
                f"{path}: the pickle references code ({detail}), so torch.load(weights_only=True) refused it: loading "
                f"it could run arbitrary code. If you trust the file, load it with allow_unsafe_pickle=True "
                f"(CLI flag --allow_unsafe_pickle)."
            ) from None
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({detail}); if it is a trusted pickle that "
                              f"weights_only loading cannot read, see allow_unsafe_pickle / --allow_unsafe_pickle"
                              ) from None
    except (RuntimeError, EOFError, OSError, ValueError) as e:
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({e})") from None
    if allow_unsafe_pickle:
        logger.warning("loaded %s with weights_only=False (allow_unsafe_pickle)", path)
    state_dict = obj.get("state_dict", obj) if isinstance(obj, dict) else None
    if not isinstance(state_dict, dict) or not any(isinstance(v, torch.Tensor) for v in state_dict.values()):
        raise CheckpointError(f"{path}: expected a Lightning checkpoint with a 'state_dict' of tensors "
                              f"(or a plain state dict); found {type(obj).__name__} without one")
    return state_dict


def _unpickler_detail(message: str) -> str:
    """The informative line of torch's weights_only error (the rest is generic advice)."""
    for line in message.splitlines():
        if any(word in line for word in ("GLOBAL", "Unsupported", "WeightsUnpickler")):
            line = line.split("WeightsUnpickler error:")[-1].split(" Please use")[0].strip()
            if line:
                return line
    return message.splitlines()[0] if message else "unknown error"


def _select_weights(state_dict: Dict, use_ema: bool, path: Path) -> Dict[str, torch.Tensor]:
    """encoder.* / decoder.* weights, or their `model_ema.<name without dots>` copies when asked and present."""
    raw = {k: v for k, v in state_dict.items() if k.startswith(("encoder.", "decoder."))}
    ema_names = {EMA_PREFIX + k.replace(".", ""): k for k in raw}
    if len(ema_names) != len(raw):
        raise CheckpointError(f"{path}: parameter names collide once dots are removed; cannot map EMA weights")
    found = {ema_key: name for ema_key, name in ema_names.items() if ema_key in state_dict}
    if not use_ema:
        return raw
    if not found:
        if any(k.startswith(EMA_PREFIX) for k in state_dict):
            logger.warning("%s: its model_ema.* entries match no encoder/decoder weight; using the raw weights", path)
        else:
            logger.info("%s has no EMA weights; using the raw weights", path)
        return raw
    missing = sorted(name for ema_key, name in ema_names.items() if ema_key not in found)
    if missing:
        raise CheckpointError(f"{path}: EMA copies are missing for {len(missing)} weights "
                              f"({_listing(missing)}); pass use_ema=False to load the raw weights")
    return {name: state_dict[ema_key] for ema_key, name in found.items()}


def infer_config(state_dict: Dict[str, torch.Tensor], source: str = "checkpoint") -> VQConfig:
    """Architecture from weight shapes (loss weights and resolution keep their defaults).

    Falls back to VQConfig() when the encoder weights needed are absent; the fit check then lists what is wrong.
    """
    try:
        conv_in, conv_out = state_dict["encoder.conv_in.weight"], state_dict["encoder.conv_out.weight"]
        base, in_channels, z_channels = conv_in.shape[0], conv_in.shape[1], conv_out.shape[0]
        levels = sorted({int(m.group(1)) for k in state_dict if (m := re.match(r"encoder\.down\.(\d+)\.", k))})
        blocks = {int(m.group(1)) for k in state_dict if (m := re.match(r"encoder\.down\.0\.block\.(\d+)\.", k))}
        ch_mult = [state_dict[f"encoder.down.{i}.block.0.conv1.weight"].shape[0] // base for i in levels]
        out_channels = state_dict["decoder.conv_out.weight"].shape[0] if "decoder.conv_out.weight" in state_dict else 3
        return VQConfig(in_channels=in_channels, z_channels=z_channels, out_channels=out_channels,
                        base_channels=base, ch_mult=ch_mult, num_res_blocks=len(blocks), codebook_size=2 ** z_channels)
    except (KeyError, ConfigError, IndexError) as e:
        logger.warning("%s: could not infer the tokenizer architecture (%s); assuming the default VQConfig", source, e)
        return VQConfig()


def _listing(names) -> str:
    names = list(names)
    more = f", ... ({len(names) - MAX_LISTED_KEYS} more)" if len(names) > MAX_LISTED_KEYS else ""
    return ", ".join(names[:MAX_LISTED_KEYS]) + more


def _check_fits(model: VQModel, state_dict: Dict[str, torch.Tensor], source) -> None:
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    mismatched = sorted(f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(v.shape)}"
                        for k, v in expected.items() if k in state_dict and state_dict[k].shape != v.shape)
    if not (missing or unexpected or mismatched):
        return
    c = model.config
    lines = [f"{source} does not fit the tokenizer config (z_channels={c.z_channels}, base_channels={c.base_channels}, "
             f"ch_mult={c.ch_mult}, num_res_blocks={c.num_res_blocks}):"]
    for what, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatches", mismatched)):
        if keys:
            lines.append(f"  {what} ({len(keys)}): {_listing(keys)}")
    lines.append("Pass the config the checkpoint was trained with (or none, to infer it from the weights).")
    raise CheckpointError("\n".join(lines))
