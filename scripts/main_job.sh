#!/usr/bin/env bash
# The main job: set up .venv, then train and evaluate PAC-DP end to end, offline.
#
#   bash scripts/main_job.sh                                        # robomimic Lift, scripted demos (offline default)
#   bash scripts/main_job.sh PATH/TO/pusht_cchi_v7_replay.zarr      # PushT, the real human demos (offline)
#   bash scripts/main_job.sh lerobot/pusht_keypoints                 # PushT from the hub
#
# Each run records or converts the demonstrations, trains with lerobot-train, rolls out with lerobot-eval
# and prints the success rate and the held-out denoising error (NPE). Knobs: STEPS, EVAL_EPISODES, OUT,
# and DEMOS (Lift: how many to record) or EPISODES (PushT: which demos, e.g. 0-29).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
if [ $# -eq 0 ]; then
  out="${OUT:-outputs/main_job_lift}"
  example=(examples/lift_end_to_end.sh "$out")
else
  out="${OUT:-outputs/main_job_pusht}"
  export STEPS="${STEPS:-1000}" EPISODES="${EPISODES:-0-29}" EVAL_EPISODES="${EVAL_EPISODES:-5}"
  example=(examples/pusht_end_to_end.sh "$1" "$out")
fi
mkdir -p "$(dirname "$out")"
start=$SECONDS
# LeRobot logs a harmless torchcodec traceback when FFmpeg is missing (state-only data decodes no video).
bash "${example[@]}" 2>&1 | tee "$out.log" | grep --line-buffered -v -E "torchcodec|libav|FFmpeg|OSError|^\s|^Traceback|^\[end of|^The above|^$|Could not load"
npe=$(grep -o "eval_loss=[0-9.]*" "$out.log" | tail -1 | cut -d= -f2 || true)
echo "held-out denoising error (posterior mean, last checkpoint): ${npe:-n/a}"
echo "main job finished in $(( (SECONDS - start) / 60 )) min $(( (SECONDS - start) % 60 )) s; full log: $out.log"
