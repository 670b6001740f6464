#!/usr/bin/env bash
# The measured result behind results/uncertainty: does PAC-DP's posterior spread predict that a rollout fails?
#
#   bash benchmarks/uncertainty_study.sh PACDP_CHECKPOINT DP_CHECKPOINT OUT [ENV FLAGS...]
#   OOD_SHIFTS=[0.05,0.1,0.2] bash benchmarks/uncertainty_study.sh outputs/dev/lr6e-3/checkpoints/001000/pretrained_model \
#       outputs/dev/dp6e-3/checkpoints/001000/pretrained_model results/uncertainty --env.type=robomimic --env.task=lift
#
# Both checkpoints are rolled out N_EPISODES times (default 100) on the same seeds (SEED, default 1000), side by
# side, one torch thread each, recording K = SAMPLES (default 8) chunks per decision; then one analysis of the
# PAC-DP episodes with the DP twin's noise spread as the second baseline writes OUT/summary.json and the plots,
# with the out-of-distribution check of the PAC-DP checkpoint (robomimic) when OOD_SHIFTS is set (its starts
# are seeded after the rollouts'). The recordings stay in OUT/recordings/{pacdp,dp}/rollouts.
set -euo pipefail
cd "$(dirname "$0")/.."
pacdp="${1:?usage: $0 PACDP_CHECKPOINT DP_CHECKPOINT OUT [ENV FLAGS...]}"
dp="${2:?usage: $0 PACDP_CHECKPOINT DP_CHECKPOINT OUT [ENV FLAGS...]}"
out="${3:?usage: $0 PACDP_CHECKPOINT DP_CHECKPOINT OUT [ENV FLAGS...]}"
shift 3
bin=.venv/bin
export HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1
episodes="${N_EPISODES:-100}" seed="${SEED:-1000}"
common=(--batch_size="${BATCH_SIZE:-10}" --samples="${SAMPLES:-8}" "$@")
mkdir -p "$out/recordings"
"$bin/pacdp-uncertainty" --checkpoint="$dp" --n_episodes="$episodes" --seed="$seed" "${common[@]}" --output_dir="$out/recordings/dp" > "$out/recordings/dp.log" 2>&1 &
dp_job=$!
trap 'kill $dp_job 2>/dev/null || true' EXIT
"$bin/pacdp-uncertainty" --checkpoint="$pacdp" --n_episodes="$episodes" --seed="$seed" "${common[@]}" --output_dir="$out/recordings/pacdp" > "$out/recordings/pacdp.log" 2>&1 \
  || { tail -3 "$out/recordings/pacdp.log"; exit 1; }
wait "$dp_job" || { tail -3 "$out/recordings/dp.log"; exit 1; }
trap - EXIT
"$bin/pacdp-uncertainty" --episodes="[$out/recordings/pacdp/rollouts]" --twin_episodes="[$out/recordings/dp/rollouts]" \
  --checkpoint="$pacdp" --n_episodes=0 --seed=$(( seed + episodes )) ${OOD_SHIFTS:+--ood_shifts="$OOD_SHIFTS"} "${common[@]}" \
  --output_dir="$out"
