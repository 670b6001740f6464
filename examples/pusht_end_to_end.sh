#!/usr/bin/env bash
# PushT with PAC-DP, end to end: convert the demos, train with lerobot-train, roll out with lerobot-eval.
#
#   bash examples/pusht_end_to_end.sh SOURCE [OUTPUT_DIR]
#
# SOURCE is either a path to Diffusion Policy's PushT replay buffer (pusht_cchi_v7_replay.zarr, 206
# human demos; converted locally, fully offline) or a hub dataset id laid out like
# lerobot/pusht_keypoints (downloaded by LeRobot; needs the hub).
# Sizes come from configs/pusht/pacdp_cpu.json (a small U-Net for CPUs); override any field on the
# command line (STEPS=..., EPISODES=..., or edit the lerobot-train line). Paper scale: configs/pusht/pacdp_paper.json.
set -euo pipefail
source="${1:?usage: $0 PATH/TO/pusht_cchi_v7_replay.zarr|lerobot/pusht_keypoints [OUTPUT_DIR]}"
out="${2:-outputs/pusht_pacdp}"
steps="${STEPS:-2000}"
episodes="${EPISODES:-0-39}"
eval_episodes="${EVAL_EPISODES:-10}"
bin="$(dirname "$0")/../.venv/bin"
[ -x "$bin/lerobot-train" ] || bin="$(dirname "$(command -v lerobot-train)")"

if [ -e "$source" ]; then
  export HF_HUB_OFFLINE=1
  echo "== 1/3 converting PushT demos $episodes from $source"
  "$bin/pacdp-convert-pusht" --zarr "$source" --output-root "$out/data" --episodes "$episodes" --overwrite
  dataset=(--dataset.repo_id=local/pusht --dataset.root="$out/data")
else
  echo "== 1/3 using hub dataset $source, demos $episodes"
  episode_list=$("$bin/python" -c "from lerobot_pacdp.episodes import parse_episodes as p; import sys; print(str(p(sys.argv[1])).replace(' ', ''))" "$episodes")
  dataset=(--dataset.repo_id="$source" --dataset.episodes="$episode_list")
fi

echo "== 2/3 training PAC-DP for $steps steps (10% of the demos held out for the NPE)"
rm -rf "$out/train"
"$bin/lerobot-train" --config_path=configs/pusht/pacdp_cpu.json \
  "${dataset[@]}" \
  --steps="$steps" --output_dir="$out/train" --wandb.enable=false

echo "== 3/3 rolling out the last checkpoint in gym-pusht ($eval_episodes episodes)"
rm -rf "$out/eval"
"$bin/lerobot-eval" --policy.path="$out/train/checkpoints/last/pretrained_model" \
  --env.type=pusht --env.obs_type=environment_state_agent_pos \
  --eval.n_episodes="$eval_episodes" --eval.batch_size=5 --eval.use_async_envs=false \
  --output_dir="$out/eval"
"$bin/python" -c "import json, sys; o = json.load(open(sys.argv[1]))['overall']; print(f'success rate: {o[\"pc_success\"]:.1f}% over {o[\"n_episodes\"]} episodes')" "$out/eval/eval_info.json"
