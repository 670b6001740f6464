#!/usr/bin/env bash
# The main job: set up .venv, then train and evaluate PAC-DP end to end, offline.
#
#   bash scripts/main_job.sh                                        # robomimic Lift, scripted demos (offline default)
#   bash scripts/main_job.sh PATH/TO/pusht_cchi_v7_replay.zarr      # PushT, the real human demos (offline)
#   bash scripts/main_job.sh lerobot/pusht_keypoints                 # PushT from the hub
#
# Each run records or converts the demonstrations, trains with lerobot-train (progress bar and a loss line as
# it goes), rolls out with lerobot-eval (Lift 100 episodes, PushT 50, distinct seeds, a few as videos), measures the
# held-out denoising error (NPE) and writes OUT/summary.json: success rate with its 95% interval, NPE,
# training steps, wall time. Knobs: STEPS, EVAL_EPISODES, OUT, and DEMOS (Lift: how many to record) or
# EPISODES (PushT: which demos, default all 206: 0-205).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
if [ $# -eq 0 ]; then
  out="${OUT:-outputs/main_job_lift}"
  example=(examples/lift_end_to_end.sh "$out")
else
  out="${OUT:-outputs/main_job_pusht}"
  example=(examples/pusht_end_to_end.sh "$1" "$out")
fi
mkdir -p "$out"
start=$SECONDS
bash "${example[@]}" 2>&1 | tee "$out.log" | .venv/bin/python scripts/drop_torchcodec_noise.py
echo "main job finished in $(( (SECONDS - start) / 60 )) min $(( (SECONDS - start) % 60 )) s after set-up; summary: $out/summary.json; full log: $out.log"
