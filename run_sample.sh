#!/usr/bin/env bash
# The main job on the embedded sample world (run ./build.sh first):
#   1. train a small action-conditioned GENIE on data/sample/train -> data/genie_model/final_checkpt, as the recipe
#      file RECIPE (default recipes/sample_world.json) says: the model (the previous-frame pointer at radius 4,
#      conditioned on the buttons the walker held, averaged over each window step: what a player commands), the
#      training (1600 steps of 2 windows, half of them played backward in time with the buttons mirrored, so that
#      walking back learns from walking forward; Muon for the transformer's matrices, AdamW for the rest:
#      common/muon.py; learning rate 1e-2 decaying linearly to zero; weight decay 0.4) and the decoding saved with
#      the checkpoint
#   2. generate from held-out prompts of data/sample/val, playing their recorded actions
#      -> data/genie_model/generated (tokens)
#   3. decode them into a GIF and a comic strip          -> data/genie_model/*.gif, *.png
#   4. evaluate with the challenge metrics, the copy-the-last-frame baselines and the rollout protocol (greedy, and
#      sampled: whole tokens at temperature 1) -> data/genie_model/*.json
#   5. play it for 64 steps (27 s) from real starts, replaying the recorded buttons, scored against the real frames
#      beside the tokenizer's reconstruction and holding the last real frame (evaluate.py --protocol play)
#      -> data/genie_model/metrics_play*.json, play_curves.png, play_drive.gif
#   6. print the commands that play the model in a browser (play.py) and rank policies inside it
# Futures are decoded as the checkpoint's decoding.json says (the recipe's: whole tokens at temperature 1, the
# pointer's --copy_bias 2, greedy copies from the single most weighted neighbour); the GIF, the comic and the greedy
# rollouts add --temperature 0.
# Extra arguments go to train.py after the recipe's values and override them (e.g. ./run_sample.sh --max_train_steps
# 50 for a smoke test). The environment variables PY (the Python; default venv/bin/python), SAMPLE_DIR, OUT, RECIPE,
# GENIE_CONFIG (a model config in place of the recipe's model), NUM_EXAMPLES, EXAMPLE_STRIDE,
# GENERATE_ARGS (extra generate.py flags; set it empty for a GENIE_CONFIG without actions, e.g.
# GENIE_CONFIG=genie/configs/sample_world.json GENERATE_ARGS=), EVAL_ARGS, LPIPS_EVAL_ARGS and ROLLOUT_EVAL_ARGS
# (extra evaluate.py flags of the three evaluations), SAMPLED_ROLLOUT_ARGS (extra flags of the sampled rollout
# evaluation; SKIP_SAMPLED=1 skips it), WEIGHT_DECAY (train.py's; the recipe's 0.4 unless set) change the defaults below;
# PLAY_ARGS (extra flags of the play protocol; SKIP_PLAY=1 skips it);
# SKIP_BASELINES=1 skips evaluation.baselines (the data's copy and lookup baselines, the same for every model: slow on a
# large world, and known after one run).
# STALL_RATIO (off unless set) turns on the stall rule for the futures (--stall_ratio: a future whose frame changes
# at most that fraction of what the prompt's frames change holds that frame; docs/experiments.md measures 0.66 for
# the model without actions: GENIE_CONFIG=genie/configs/sample_world.json GENERATE_ARGS= WEIGHT_DECAY=0.05
# STALL_RATIO=0.66 ./run_sample.sh --lr_scheduler_type cosine, the weight decay and schedule it was measured with).
# run_gpu.sh is this job at a GPU's scale.
# Sets of unseen maps: each folder of UNSEEN_DIRS (default "data/unseen data/unseen2 data/unseen3", the three sets
# ./build.sh --unseen makes) that holds a val split is also evaluated (teacher-forced and rollout) -> metrics_NAME.json,
# metrics_rollout_NAME.json, metrics_rollout_sampled_NAME.json, NAME being the folder's name; folders without one are
# skipped. UNSEEN_DIR=DIR (one folder) evaluates DIR alone, its files named metrics_unseen*.json as before.
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac
cd "$(dirname "$0")"
PY=${PY:-venv/bin/python}
SAMPLE_DIR=${SAMPLE_DIR:-data/sample}
OUT=${OUT:-data/genie_model}
TRAIN=$SAMPLE_DIR/train
VAL=$SAMPLE_DIR/val
# the generated futures decode as the checkpoint says (decoding.json, from the recipe), plus the stall rule if asked
STALL_ARGS="${STALL_RATIO:+--stall_ratio $STALL_RATIO}"
[ -f "$TRAIN/metadata.json" ] || { echo "run_sample.sh: $TRAIN is missing; run ./build.sh first" >&2; exit 1; }

# the run's recipe file (model, training settings, decoding); GENIE_CONFIG and WEIGHT_DECAY override its values
"$PY" train.py --recipe "${RECIPE:-recipes/sample_world.json}" ${GENIE_CONFIG:+--genie_config "$GENIE_CONFIG"} \
  ${WEIGHT_DECAY:+--weight_decay "$WEIGHT_DECAY"} --train_data_dir "$TRAIN" --val_data_dir "$VAL" --output_dir "$OUT" \
  --resume_from_checkpoint latest "$@"

"$PY" generate.py --checkpoint_dir "$OUT/final_checkpt" --val_data_dir "$VAL" --output_dir "$OUT/generated" \
  --num_prompt_frames 8 --num_examples "${NUM_EXAMPLES:-4}" --example_stride "${EXAMPLE_STRIDE:-2500}" --temperature 0 \
  $STALL_ARGS ${GENERATE_ARGS---actions_from_data}
"$PY" visualize.py --token_dir "$OUT/generated" --output_dir "$OUT" --fps 4

# evaluate_tf DIR / evaluate_rollout DIR: the two protocols on a token dataset, with the env's extra flags
evaluate_tf() {
  "$PY" evaluate.py --checkpoint_dir "$OUT/final_checkpt" --val_data_dir "$1" --skip_lpips \
    ${EVAL_ARGS---max_examples 270 --spread_examples}
}
# evaluate_rollout DIR [FLAGS]: FLAGS override the checkpoint's sampler (none: as the checkpoint decodes)
evaluate_rollout() {
  local dir=$1; shift
  "$PY" evaluate.py --checkpoint_dir "$OUT/final_checkpt" --val_data_dir "$dir" --protocol rollout \
    ${ROLLOUT_EVAL_ARGS:---max_examples 48 --spread_examples --num_prompt_frames 8} $STALL_ARGS "$@"
}
# the sampled rollouts: the checkpoint's decoding (whole tokens drawn at temperature 1), SAMPLED_ROLLOUT_ARGS added
SAMPLED=1
[ -z "${SKIP_SAMPLED:-}" ] || SAMPLED=
# CE and accuracy on 270 validation windows spread over the split (a third of them, to fit the CPU budget;
# EVAL_ARGS= evaluates all 810); LPIPS (decodes every frame, slow on CPU) on the first 60.
evaluate_tf "$VAL" | tee "$OUT/eval.log"
"$PY" evaluate.py --checkpoint_dir "$OUT/final_checkpt" --val_data_dir "$VAL" ${LPIPS_EVAL_ARGS:---max_examples 60} \
  | tee "$OUT/eval_lpips.log"
[ -n "${SKIP_BASELINES:-}" ] || "$PY" diagnose.py baselines --train_data_dir "$TRAIN" --val_data_dir "$VAL" | tee "$OUT/baselines.log"
# The 1X sampling challenge's form: 8 prompt frames, the other 8 generated free-running, PSNR / SSIM / LPIPS per
# horizon against holding the last prompt frame.
evaluate_rollout "$VAL" --temperature 0 | tee "$OUT/eval_rollout.log"
[ -z "$SAMPLED" ] || evaluate_rollout "$VAL" ${SAMPLED_ROLLOUT_ARGS:-} | tee "$OUT/eval_rollout_sampled.log"
# evaluate_play DIR FIGURES: the play protocol on a sample world split (its raw frames beside it), figures to FIGURES
evaluate_play() {
  "$PY" evaluate.py --checkpoint_dir "$OUT/final_checkpt" --val_data_dir "$1" --protocol play --figures_dir "$2" \
    ${PLAY_ARGS:-}
}
[ -n "${SKIP_PLAY:-}" ] || evaluate_play "$VAL" "$OUT" | tee "$OUT/eval_play.log"
# evaluate_unseen NAME DIR: the protocols on DIR/val -> metrics_NAME.json, metrics_rollout[_sampled]_NAME.json,
# metrics_play_NAME.json (figures in OUT/play_NAME); nothing when DIR has no val split
SCORED_UNSEEN=""
evaluate_unseen() {
  local name=$1 dir=$2
  [ -f "$dir/val/metadata.json" ] || return 0
  SCORED_UNSEEN+=" $OUT/metrics*_$name.json"
  evaluate_tf "$dir/val" | tee "$OUT/eval_$name.log"
  evaluate_rollout "$dir/val" --temperature 0 | tee "$OUT/eval_rollout_$name.log"
  [ -z "$SAMPLED" ] || evaluate_rollout "$dir/val" ${SAMPLED_ROLLOUT_ARGS:-} | tee "$OUT/eval_rollout_sampled_$name.log"
  tail -n 1 "$OUT/eval_$name.log" > "$OUT/metrics_$name.json"
  tail -n 1 "$OUT/eval_rollout_$name.log" > "$OUT/metrics_rollout_$name.json"
  [ -z "$SAMPLED" ] || tail -n 1 "$OUT/eval_rollout_sampled_$name.log" > "$OUT/metrics_rollout_sampled_$name.json"
  if [ -z "${SKIP_PLAY:-}" ]; then
    evaluate_play "$dir/val" "$OUT/play_$name" | tee "$OUT/eval_play_$name.log"
    tail -n 1 "$OUT/eval_play_$name.log" > "$OUT/metrics_play_$name.json"
  fi
}
if [ -n "${UNSEEN_DIR:-}" ]; then
  evaluate_unseen unseen "$UNSEEN_DIR"
else
  for dir in ${UNSEEN_DIRS-data/unseen data/unseen2 data/unseen3}; do evaluate_unseen "$(basename "$dir")" "$dir"; done
fi
tail -n 1 "$OUT/eval.log" > "$OUT/metrics.json"
tail -n 1 "$OUT/eval_lpips.log" > "$OUT/metrics_lpips.json"
[ -n "${SKIP_BASELINES:-}" ] || tail -n 1 "$OUT/baselines.log" > "$OUT/baselines.json"
tail -n 1 "$OUT/eval_rollout.log" > "$OUT/metrics_rollout.json"
[ -z "$SAMPLED" ] || tail -n 1 "$OUT/eval_rollout_sampled.log" > "$OUT/metrics_rollout_sampled.json"
[ -n "${SKIP_PLAY:-}" ] || tail -n 1 "$OUT/eval_play.log" > "$OUT/metrics_play.json"
echo "model: $OUT/final_checkpt   pictures: $OUT/*.gif $OUT/*.png"
echo "metrics: $OUT/metrics.json (LPIPS: $OUT/metrics_lpips.json; copy baselines: $OUT/baselines.json;"
echo "         rollouts: $OUT/metrics_rollout.json, sampled: $OUT/metrics_rollout_sampled.json;"
echo "         a minute of play against the real frames: $OUT/metrics_play.json, $OUT/play_curves.png, $OUT/play_drive.gif)"
[ -z "$SCORED_UNSEEN" ] || echo "unseen maps:$SCORED_UNSEEN"
echo "play it in a browser: $PY play.py --checkpoint_dir $OUT/final_checkpt --data_dir $VAL"
echo "rank policies inside it: $PY evaluate.py --protocol policies --checkpoint_dir $OUT/final_checkpt"
