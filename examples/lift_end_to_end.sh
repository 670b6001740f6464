#!/usr/bin/env bash
# Robomimic Lift with PAC-DP, end to end and fully offline: scripted demonstrations -> LeRobotDataset ->
# lerobot-train -> lerobot-eval in robosuite 1.5.
#
#   bash examples/lift_end_to_end.sh [OUTPUT_DIR]
#
# Knobs (environment variables): DEMOS (scripted demos to record), STEPS (training steps),
# EVAL_EPISODES (rollouts). Sizes come from configs/robomimic/lift_cpu.json (a CPU preset); the
# paper's setting is configs/robomimic/lift.json (on the released `ph` file, see the README).
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-outputs/lift_pacdp}"
demos="${DEMOS:-40}"
steps="${STEPS:-1000}"
eval_episodes="${EVAL_EPISODES:-10}"
bin=.venv/bin
[ -x "$bin/lerobot-train" ] || bin="$(dirname "$(command -v lerobot-train)")"
export HF_HUB_OFFLINE=1

echo "== 1/4 recording $demos scripted Lift demonstrations (robosuite 1.5, privileged cube pose, action noise 0.05)"
mkdir -p "$out"
"$bin/pacdp-scripted-demos" --task lift --num-demos "$demos" --seed 0 --action-noise 0.05 \
  --output "$out/lift_scripted.hdf5" --overwrite

echo "== 2/4 converting them into a LeRobotDataset ($out/data)"
"$bin/pacdp-convert-robomimic" --hdf5 "$out/lift_scripted.hdf5" --output-root "$out/data" \
  --repo-id local/robomimic_lift_scripted --overwrite

echo "== 3/4 training PAC-DP for $steps steps (configs/robomimic/lift_cpu.json; 10% of the demos held out for the NPE)"
rm -rf "$out/train"
"$bin/lerobot-train" --config_path=configs/robomimic/lift_cpu.json --dataset.root="$out/data" \
  --steps="$steps" --save_freq="$steps" --eval_steps="$steps" --output_dir="$out/train" --wandb.enable=false

echo "== 4/4 rolling out the last checkpoint in robosuite Lift ($eval_episodes episodes)"
rm -rf "$out/eval"
"$bin/lerobot-eval" --policy.path="$out/train/checkpoints/last/pretrained_model" \
  --env.type=robomimic --env.task=lift \
  --eval.n_episodes="$eval_episodes" --eval.batch_size=5 --eval.use_async_envs=false \
  --output_dir="$out/eval"
"$bin/python" -c "import json, sys; o = json.load(open(sys.argv[1]))['overall']; print(f'success rate: {o[\"pc_success\"]:.1f}% over {o[\"n_episodes\"]} episodes')" "$out/eval/eval_info.json"
