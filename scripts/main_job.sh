#!/usr/bin/env bash
# The main job: set up .venv, then train and evaluate PAC-DP end to end, offline.
#
#   bash scripts/main_job.sh PATH/TO/pusht_cchi_v7_replay.zarr     # offline
#   bash scripts/main_job.sh lerobot/pusht_keypoints                # from the hub
#
# PushT: (convert ->) lerobot-train -> lerobot-eval, printing the held-out denoising error (NPE) and
# the success rate. Knobs: STEPS, EPISODES, EVAL_EPISODES, OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
source="${1:?usage: bash scripts/main_job.sh PATH/TO/pusht_cchi_v7_replay.zarr|lerobot/pusht_keypoints}"
bash scripts/bootstrap.sh
out="${OUT:-outputs/main_job}"
export STEPS="${STEPS:-1000}" EPISODES="${EPISODES:-0-29}" EVAL_EPISODES="${EVAL_EPISODES:-5}"
bash examples/pusht_end_to_end.sh "$source" "$out" 2>&1 | tee "$out.log" | grep -v -E "torchcodec|libav|FFmpeg|OSError|^\s|^Traceback|^\[end of|^The above|^$|Could not load"
npe=$(grep -o "eval_loss=[0-9.]*" "$out.log" | tail -1 | cut -d= -f2 || true)
echo "held-out denoising error (posterior mean, last checkpoint): ${npe:-n/a}"
