#!/usr/bin/env bash
# The measured curves behind the CPU recipes: DP (pacdp bayesian=false) and PAC-DP trained side by side on the
# same data with the same recipe, then every checkpoint's held-out NPE and success rate (pacdp-metrics: NPE on the
# held-out demos, EVAL_EPISODES rollouts per checkpoint). Results land in OUT/curves (metrics.csv, curves.png);
# results/recipes/ holds the committed ones.
#
#   bash benchmarks/recipe_curves.sh lift  [OUT]    # 40 scripted Lift demos (as the main job), configs/robomimic/lift_cpu.json
#   bash benchmarks/recipe_curves.sh pusht [OUT]    # all 206 PushT demos from ../shared, configs/pusht/pacdp_cpu.json
#
# Knobs: STEPS, SAVE_FREQ, LR, WARMUP (override the config's recipe), EVAL_EPISODES (default 20), EPISODES (PushT's
# demos, default 0-205).
set -euo pipefail
cd "$(dirname "$0")/.."
task="${1:?usage: $0 lift|pusht [OUT]}"
out="${2:-outputs/recipe_$task}"
bin=.venv/bin
export HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1   # two runs side by side, one thread each
mkdir -p "$out"
case "$task" in
  lift)
    "$bin/pacdp-scripted-demos" --task=lift --num_demos=40 --seed=0 --action_noise=0.05 --output="$out/demos.hdf5" --overwrite=true
    "$bin/pacdp-convert-robomimic" --hdf5="$out/demos.hdf5" --output_root="$out/data" --repo_id=local/robomimic_lift_scripted --overwrite=true
    config=configs/robomimic/lift_cpu.json; data=(--dataset.root="$out/data")
    env=(--env.type=robomimic --env.task=lift) ;;
  pusht)
    "$bin/pacdp-convert-pusht" --zarr=../shared/data/pusht/pusht_cchi_v7_replay.zarr --output_root="$out/data" --episodes="${EPISODES:-0-205}" --overwrite=true
    config=configs/pusht/pacdp_cpu.json; data=(--dataset.repo_id=local/pusht --dataset.root="$out/data")
    env=(--env.type=pusht --env.obs_type=environment_state_agent_pos) ;;
  *) echo "unknown task $task (lift | pusht)" >&2; exit 2 ;;
esac
recipe=(${STEPS:+--steps=$STEPS} ${SAVE_FREQ:+--save_freq=$SAVE_FREQ --eval_steps=$SAVE_FREQ}
        ${LR:+--policy.optimizer_lr=$LR} ${WARMUP:+--policy.scheduler_warmup_steps=$WARMUP})
rm -rf "$out/dp" "$out/pacdp"
"$bin/lerobot-train" --config_path="$config" "${data[@]}" "${recipe[@]}" --policy.bayesian=false \
  --output_dir="$out/dp" --wandb.enable=false > "$out/dp.log" 2>&1 &
"$bin/lerobot-train" --config_path="$config" "${data[@]}" "${recipe[@]}" \
  --output_dir="$out/pacdp" --wandb.enable=false > "$out/pacdp.log" 2>&1 &
wait
"$bin/pacdp-metrics" --runs="[$out/dp,$out/pacdp]" --labels="[DP,PAC-DP]" --nll=false "${env[@]}" \
  --eval_episodes="${EVAL_EPISODES:-20}" --eval_batch_size=2 --output_dir="$out/curves"
.venv/bin/python benchmarks/plot_recipe_curves.py --metrics "$out/curves/metrics.json" --log DP="$out/dp.log" \
  --log PAC-DP="$out/pacdp.log" --log-freq 100 --title "$task: DP and PAC-DP, ${EVAL_EPISODES:-20} rollouts per checkpoint" \
  --output "$out/curves"
echo "curves: $out/curves/curves.png (training losses in $out/dp.log, $out/pacdp.log)"
