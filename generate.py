"""Generate future frames (as tokens) with a GENIE checkpoint from validation windows.

    python generate.py --checkpoint_dir data/genie_model/final_checkpt --output_dir data/genie_generated
    python visualize.py --token_dir data/genie_generated

For each of `--num_examples` windows starting at dataset index `--example_ind`, the first `--num_prompt_frames`
frames are the prompt and the remaining `window_size - num_prompt_frames` frames are predicted with MaskGIT
(autoregressively in time, or with `--teacher_force_time` from the ground truth of all earlier frames).
Frames are sampled as the checkpoint's decoding.json says (genie/decoding.py; the published checkpoints: greedy);
each decoding flag overrides one value, and the output's metadata.json records what was used.
The output directory uses the token dataset layout (video.bin + metadata.json, written atomically); each example
contributes `2 * window_size - num_prompt_frames` frames, ordered prompt | predictions | ground truth.

Action-conditioned checkpoints (genie/actions.py) get the window's actions from the dataset under the challenge's
rule (only the prompt's rows are known; later frames get "no action"), or are played:
    python generate.py ... --latent_actions 3,3,1,0,2,2,5,7   # one LAM latent action per generated frame
    python generate.py ... --actions_from_data                 # the data's own actions for generated frames
    python visualize.py --token_dir data/genie_generated --label_action latent_action
With latent actions, actions/latent_action.bin in the output holds each output frame's latent action (-1: none;
prompt and ground-truth frames: the dataset's ids when it has them).
"""
import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from tqdm.auto import tqdm

from common.cli import add_device_arg, add_num_threads_arg, apply_cpu_settings, resolve_device, run_main, setup_logging
from common.errors import DataMismatchError
from data import RawTokenDataset, write_token_dataset
from training.action_streams import LATENT_ACTION_NAME, prepare_action_streams, stack_streams, window_actions
from genie.config import check_dataset_matches
from evaluation.cli import add_decoding_args, check_decoding_args, decoding_overrides
from evaluation.protocols import apply_decoding
from genie.inference import generate_frames, teacher_forced
from genie.model import STMaskGIT

logger = logging.getLogger("generate")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="generate.py",
                                description="Generate future frames (tokens) from a GENIE checkpoint.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--val_data_dir", default="data/sample/val" if Path("data/sample/val").exists() else "data/val_v1.1",
                   help="Token dataset directory whose windows provide the prompts and the ground truth.")
    p.add_argument("--checkpoint_dir", default="data/genie_model/final_checkpt",
                   help="Hugging Face checkpoint directory (config.json + model.safetensors).")
    p.add_argument("--output_dir", default="data/genie_generated",
                   help="Where video.bin + metadata.json are written (replaced if it exists).")
    p.add_argument("--num_prompt_frames", type=int, default=8, help="Ground-truth frames given as context.")
    p.add_argument("--window_size", type=int, default=16,
                   help="Frames per window (must equal the checkpoint's T); window_size - num_prompt_frames are "
                        "generated.")
    p.add_argument("--stride", type=int, default=15, help="Frames between consecutive frames of a window.")
    p.add_argument("--example_ind", type=int, default=0, help="Dataset index of the first window to generate on.")
    p.add_argument("--num_examples", type=int, default=1, help="Windows to generate on.")
    p.add_argument("--example_stride", type=int, default=1,
                   help="Dataset indices between consecutive examples (1: consecutive windows, which overlap and "
                        "look alike; a large value spreads the examples over the dataset).")
    p.add_argument("--batch_size", type=int, default=8, help="Windows generated at once.")
    p.add_argument("--teacher_force_time", action="store_true",
                   help="Predict frame t from the ground truth of frames < t (as the challenge metrics do) instead "
                        "of from the model's own earlier predictions.")
    p.add_argument("--latent_actions", default=None,
                   help="Comma-separated latent action ids (0 .. K-1 of a LAM-conditioned checkpoint) played for the "
                        "generated frames: window_size - num_prompt_frames ids, or one id for all of them.")
    p.add_argument("--actions_from_data", action="store_true",
                   help="Control mode: condition the generated frames on the dataset's own actions (real and, "
                        "unless --latent_actions is given, latent) instead of only the prompt's.")
    add_device_arg(p)
    add_num_threads_arg(p)
    p.add_argument("--seed", type=int, default=0, help="Seed of the sampling randomness.")
    add_decoding_args(p)
    args = p.parse_args(argv)
    for name in ("window_size", "stride", "num_examples", "example_stride", "batch_size"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not 1 <= args.num_prompt_frames < args.window_size:
        p.error(f"--num_prompt_frames must be in [1, window_size={args.window_size}), got {args.num_prompt_frames}")
    if args.example_ind < 0:
        p.error(f"--example_ind must be >= 0, got {args.example_ind}")
    if args.latent_actions is not None:
        try:
            args.latent_actions = [int(v) for v in args.latent_actions.split(",")]
        except ValueError:
            p.error(f"--latent_actions must be comma-separated integers, got {args.latent_actions!r}")
        num_new = args.window_size - args.num_prompt_frames
        if len(args.latent_actions) == 1:
            args.latent_actions = args.latent_actions * num_new
        if len(args.latent_actions) != num_new:
            p.error(f"--latent_actions: {len(args.latent_actions)} ids for {num_new} generated frames "
                    f"(window_size {args.window_size} - num_prompt_frames {args.num_prompt_frames})")
    check_decoding_args(p, args, args.num_prompt_frames)
    if args.teacher_force_time and args.stall_ratio is not None:
        p.error("--stall_ratio holds stalled free-running futures; --teacher_force_time predicts each frame from "
                "the ground truth, which never stalls")
    if args.teacher_force_time and (args.latent_actions is not None or args.actions_from_data):
        p.error("--latent_actions and --actions_from_data play generated frames; --teacher_force_time predicts each "
                "frame from the ground truth with the prompt-only action rule")
    return args


def check_compatible(model: STMaskGIT, dataset: RawTokenDataset, args) -> None:
    """Clear errors when the checkpoint, the data and the arguments disagree on shapes, vocabulary, actions or the
    examples asked for."""
    config = model.config
    check_dataset_matches(config, dataset, args.window_size, f"checkpoint {args.checkpoint_dir}")
    K = config.num_latent_actions
    if args.latent_actions is not None:
        if not K:
            raise DataMismatchError(f"--latent_actions: the checkpoint {args.checkpoint_dir} takes no latent "
                                    f"actions (num_latent_actions is 0 in its config.json)")
        bad = [a for a in args.latent_actions if not 0 <= a < K]
        if bad:
            raise DataMismatchError(f"--latent_actions: ids {bad} are outside [0, {K}) (the checkpoint's LAM "
                                    f"codebook)")
    if args.actions_from_data and not config.uses_actions:
        raise DataMismatchError(f"--actions_from_data: the checkpoint {args.checkpoint_dir} takes no actions")
    last = args.example_ind + (args.num_examples - 1) * args.example_stride
    if last >= len(dataset):
        raise DataMismatchError(f"{dataset.data_dir}: examples {args.example_ind}..{last} requested but the dataset "
                                f"has {len(dataset)} windows of {args.window_size} frames with stride {args.stride}")


def load_windows(dataset: RawTokenDataset, indices, s: int) -> torch.Tensor:
    """Ground-truth windows (B, T, H, W) int64."""
    return torch.stack([dataset[i]["tokens"] for i in indices])


def load_actions(dataset: RawTokenDataset, indices, model: STMaskGIT, use_latent: bool):
    """The windows' action rows for the model: (real actions (B, T, D) or None, latent ids (B, T) or None).

    Latent ids are only required when the model needs them from the data (no --latent_actions): a dataset without
    actions/latent_action.bin gives "no action" (id K) for the prompt otherwise.
    """
    if not model.config.uses_actions:
        return None, None
    actions_BTD, latent_BT = window_actions(model.config, stack_streams([dataset[i]["actions"] for i in indices]),
                                            use_latent, str(dataset.data_dir / "actions"))
    if model.config.num_latent_actions and latent_BT is None:
        latent_BT = torch.full((len(indices), dataset.window_size), model.config.num_latent_actions)
    return actions_BTD, latent_BT


@torch.no_grad()
def predict(model: STMaskGIT, gt_BTHW: torch.Tensor, args, generator: torch.Generator, actions_BTD=None,
            latent_BT=None) -> torch.Tensor:
    """Predicted frames (B, T - P, H, W) for ground-truth windows gt_BTHW, prompt P = args.num_prompt_frames.

    actions_BTD / latent_BT: the windows' action rows (action-conditioned models); with --latent_actions the
    generated frames' latent rows are the played ids.
    """
    kwargs = dict(**model.decoding.sampler_kwargs(), generator=generator, actions=actions_BTD,
                  latent_actions=latent_BT)
    P, T = args.num_prompt_frames, gt_BTHW.shape[1]
    if args.teacher_force_time:
        # All frames 1..T-1 from their ground-truth past in one cached pass per MaskGIT step; keep P..T-1.
        samples_BTHW, _ = teacher_forced(model, gt_BTHW, **kwargs)
        return samples_BTHW[:, P - 1:]
    control = args.actions_from_data or args.latent_actions is not None
    if args.latent_actions is not None:
        latent_BT = latent_BT.clone()
        latent_BT[:, P:] = torch.tensor(args.latent_actions, device=latent_BT.device)
        if not args.actions_from_data and actions_BTD is not None:
            # only the latent actions are played: real rows after the prompt stay unknown (NaN), so frame P still
            # sees the prompt's last real row P-1 and later frames none, as in the prompt-only rule
            actions_BTD = actions_BTD.clone()
            actions_BTD[:, P:] = float("nan")
        kwargs.update(actions=actions_BTD, latent_actions=latent_BT)
    tokens_BTHW, _ = generate_frames(model, gt_BTHW[:, :P], T - P, control=control,
                                     stall_ratio=model.decoding.stall_ratio, **kwargs)
    return tokens_BTHW[:, P:]


def played_latent_actions(latent_BT: torch.Tensor, args, K: int) -> torch.Tensor:
    """Each output frame's latent action (B, 2T - P) in the output order prompt | predictions | ground truth;
    -1 where there is none (frame 0, a frame without a known id, predictions generated without one)."""
    P = args.num_prompt_frames
    ids_BT = latent_BT.clone()
    ids_BT[:, 0] = -1  # the model never conditions frame 0 on an action
    predicted_BT = ids_BT[:, P:].clone()
    if args.latent_actions is not None:
        predicted_BT[:] = torch.tensor(args.latent_actions)
    elif not args.actions_from_data:
        predicted_BT[:] = -1
    out_BT = torch.cat([ids_BT[:, :P], predicted_BT, ids_BT[:, P:]], dim=1)
    return out_BT.masked_fill(out_BT >= K, -1)


def generate(args) -> dict:
    """Run generation; returns the metadata written."""
    device = resolve_device(args.device)
    apply_cpu_settings(args.num_threads)
    model = STMaskGIT.from_pretrained(args.checkpoint_dir).to(device)
    dataset = RawTokenDataset(args.val_data_dir, window_size=args.window_size, stride=args.stride)
    check_compatible(model, dataset, args)
    apply_decoding(model, decoding_overrides(args), args.checkpoint_dir)
    decoding = model.decoding
    s, P, T = dataset.metadata["s"], args.num_prompt_frames, args.window_size
    generator = torch.Generator(device).manual_seed(args.seed)
    K = model.config.num_latent_actions
    # the latent ids come from the data unless they are played
    use_latent = (prepare_action_streams(model.config, dataset, require_latent=args.latent_actions is None)
                  if model.config.uses_actions else False)

    outputs, latent_outputs, seconds = [], [], 0.0
    indices = list(range(args.example_ind, args.example_ind + args.num_examples * args.example_stride,
                         args.example_stride))
    for a in tqdm(range(0, len(indices), args.batch_size), desc="generate", unit="batch"):
        batch_indices = indices[a:a + args.batch_size]
        gt_BTHW = load_windows(dataset, batch_indices, s).to(device)
        actions_BTD, latent_BT = (x if x is None else x.to(device)
                                  for x in load_actions(dataset, batch_indices, model, use_latent))
        t0 = time.perf_counter()
        pred_BTHW = predict(model, gt_BTHW, args, generator, actions_BTD, latent_BT)
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds += time.perf_counter() - t0
        outputs.append(torch.cat([gt_BTHW[:, :P], pred_BTHW, gt_BTHW[:, P:]], dim=1).cpu())
        if K:
            latent_outputs.append(played_latent_actions(latent_BT.cpu(), args, K))
    video_NHW = rearrange(torch.cat(outputs), "b t h w -> (b t) h w").numpy()
    frames_per_example = 2 * T - P
    logger.info("%.4f s per generated frame (%d windows, %d frames each)", seconds / (len(indices) * (T - P)),
                len(indices), T - P)

    metadata = {k: v for k, v in dataset.metadata.items() if k != "num_images"}
    metadata.update(num_prompt_frames=P, window_size=T, num_examples=len(indices), example_ind=args.example_ind,
                    example_stride=args.example_stride,
                    frames_per_example=frames_per_example, teacher_force_time=args.teacher_force_time,
                    maskgit_steps=decoding.maskgit_steps, temperature=decoding.temperature,
                    unmask_mode=decoding.unmask_mode, stall_ratio=decoding.stall_ratio,
                    stride=args.stride, checkpoint_dir=str(args.checkpoint_dir), val_data_dir=str(args.val_data_dir))
    actions = None
    if model.copy_head is not None:
        metadata.update(copy_bias=decoding.copy_bias, greedy_tokens=decoding.greedy_tokens)
    if model.config.uses_actions:
        metadata.update(actions_from_data=args.actions_from_data, latent_actions=args.latent_actions)
    if K:
        ids_N1 = rearrange(torch.cat(latent_outputs), "b t -> (b t) 1").numpy().astype(np.float32)
        actions = {LATENT_ACTION_NAME: ids_N1}
    # One segment per example, so that windows read back from the output never mix two examples.
    segment_ids = np.repeat(np.arange(len(indices), dtype=np.int32), frames_per_example)
    write_token_dataset(args.output_dir, video_NHW, segment_ids=segment_ids, actions=actions, metadata=metadata,
                        overwrite=True)
    logger.info("wrote %d frames to %s", len(video_NHW), args.output_dir)
    return {**metadata, "num_images": len(video_NHW)}


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging()
    generate(args)
    return 0


if __name__ == "__main__":
    sys.exit(run_main("generate.py", main))
