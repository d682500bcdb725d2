#!/usr/bin/env bash
# The recipe for one CUDA GPU: a larger sample world and a larger model, evaluated exactly as run_sample.sh does.
#   1. build GPU_DIR (default data/sample_gpu): EPISODES (default 8) walks on each of TRAIN_MAPS (default the
#      default world's 16 maps: MAP01, 04, 05, 09, 10, 12, 13, 15, whose other walks validation scores, and MAP08, 11,
#      14, 16, 17, 19, 20, 21, which no validation or unseen set uses), 4x the default world's training frames, with
#      the same seed, so its validation split is byte for byte the default world's and every number compares with
#      the CPU default's
#      (rendered by WORKERS processes, default the CPU count up to 8: 108 s with two on an H200 box; tokenized on the
#      GPU in seconds). At 900 steps, 16 maps x 8 walks gave better tokens and sampled futures than 8 maps x 16 walks
#      on every unseen set, and worse on validation's familiar maps (two seeds against one; README);
#   2. ./run_sample.sh on it with the recipe file recipes/gpu_world.json (RECIPE): its model (8 layers, d_model 256:
#      10 M parameters, the main command's model otherwise), 900 steps (STEPS) of 32 windows, the first 45 (WARMUP;
#      STEPS/20 when STEPS is set) warming up, at learning rate 3e-3 (LR; the main command's 1e-2 diverges at this
#      size: on an H200 the loss left 6 near step 79 and passed 1e6 by step 120, with or without actions, while 3e-3
#      kept falling over 900 steps), the main command's weight decay (WEIGHT_DECAY, 0.4), bf16 autocast (train.py's
#      default on CUDA), eager (COMPILE=1 adds torch.compile: its ~4 min of compiling pays for itself only past
#      ~2,000 steps), a checkpoint and a validation every 300 steps, and the main command's decoding; then every
#      evaluation of the main command, teacher-forced on all validation windows, and on the unseen maps too when
#      ./build.sh --unseen made them.
# Measured on an H200 (README, "A recipe for a GPU box"): the defaults, seeds 42 and 1, about 4.5 min of training.
# Longer is not better for the futures: at STEPS=1500 (seed 42) the tokens gained on every set, but the sampled
# futures on the unseen sets that no run tunes on fell (third set +0.90 dB over holding against +1.20 / +1.23).
# The model without actions: GENIE_CONFIG=genie/configs/gpu_world.json GENERATE_ARGS= ./run_gpu.sh (STALL_RATIO
# as in run_sample.sh)
# Extra arguments go to train.py after the recipe's values and the variables' flags (they win); the environment
# variables of run_sample.sh apply
# (OUT defaults to data/genie_gpu here), and BUILD_ARGS adds flags to sample_world.build (e.g. --turn_speed).
# SKIP_BUILD=1 trains on GPU_DIR as it is (its train/ and val/ built on another machine and copied, e.g. to a GPU
# box without ViZDoom; checked against their MANIFEST.json first: 34 MB as xz-compressed tokens at the default size).
# PY picks the Python (default venv/bin/python, from ./build.sh --no-data). Without a CUDA GPU it stops, unless
# ALLOW_CPU=1 (hours to days of CPU time at these sizes; the tests run it at a tiny size).
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac
cd "$(dirname "$0")"
export PY=${PY:-venv/bin/python}
GPU_DIR=${GPU_DIR:-data/sample_gpu}
# the default world's training maps (sample_world.render.TRAIN_MAPS), spelled out so that TRAIN_MAPS can replace them
GPU_TRAIN_MAPS="MAP01 MAP04 MAP05 MAP09 MAP10 MAP12 MAP13 MAP15 MAP08 MAP11 MAP14 MAP16 MAP17 MAP19 MAP20 MAP21"
if [ "${ALLOW_CPU:-0}" != 1 ] && ! "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  echo "run_gpu.sh: no CUDA GPU visible to $PY; this recipe is sized for one (./run_sample.sh is the CPU job)." >&2
  echo "  ALLOW_CPU=1 runs it anyway." >&2
  exit 1
fi

if [ "${SKIP_BUILD:-0}" = 1 ]; then
  # a world built elsewhere and copied here (e.g. a GPU box without ViZDoom): check it arrived whole
  for split in train val; do
    if [ ! -f "$GPU_DIR/$split/metadata.json" ]; then
      echo "run_gpu.sh: SKIP_BUILD=1, but $GPU_DIR/$split/metadata.json is missing: build the world first (./run_gpu.sh" >&2
      echo "  without SKIP_BUILD, or python -m sample_world.build --output_dir DIR --train_episodes 8" >&2
      echo "  --train_maps ... on a machine with ViZDoom) and copy its train/ and val/ to $GPU_DIR" >&2
      exit 1
    fi
  done
  if ! verified=$("$PY" -m data.verify "$GPU_DIR/train" "$GPU_DIR/val" 2>&1); then
    grep -v '^OK' <<<"$verified" >&2
    echo "run_gpu.sh: $GPU_DIR is not the world its MANIFEST.json records (above); copy it again" >&2
    exit 1
  fi
else
  CPUS=$(nproc 2>/dev/null || echo 2)
  # shellcheck disable=SC2086  # TRAIN_MAPS and BUILD_ARGS are lists
  "$PY" -m sample_world.build --output_dir "$GPU_DIR" --train_episodes "${EPISODES:-8}" \
    --train_maps ${TRAIN_MAPS:-$GPU_TRAIN_MAPS} --workers "${WORKERS:-$(( CPUS < 8 ? CPUS : 8 ))}" ${BUILD_ARGS:-}
fi

export SAMPLE_DIR=$GPU_DIR OUT=${OUT:-data/genie_gpu} RECIPE=${RECIPE:-recipes/gpu_world.json}
export EVAL_ARGS=${EVAL_ARGS-}
# the variables that are set override the recipe's values
OVERRIDES=()
[ -z "${STEPS:-}" ] || OVERRIDES+=(--max_train_steps "$STEPS")
if [ -n "${WARMUP:-}" ]; then OVERRIDES+=(--num_warmup_steps "$WARMUP")
elif [ -n "${STEPS:-}" ]; then OVERRIDES+=(--num_warmup_steps "$(( STEPS / 20 ))"); fi
[ -z "${LR:-}" ] || OVERRIDES+=(--learning_rate "$LR")
[ "${COMPILE:-0}" != 1 ] || OVERRIDES+=(--compile)
exec ./run_sample.sh ${OVERRIDES[@]+"${OVERRIDES[@]}"} "$@"
