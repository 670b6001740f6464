#!/usr/bin/env bash
# PushT with PAC-DP, end to end: convert the demos, train with lerobot-train, roll out with lerobot-eval,
# summarize (success rate with its 95% interval, held-out NPE).
#
#   bash examples/pusht_end_to_end.sh SOURCE [OUTPUT_DIR]
#
# SOURCE is either a path to Diffusion Policy's PushT replay buffer (pusht_cchi_v7_replay.zarr, 206
# human demos; converted locally, fully offline) or a hub dataset id laid out like
# lerobot/pusht_keypoints (downloaded by LeRobot; needs the hub).
# Sizes come from configs/pusht/pacdp_cpu.json (a small U-Net for CPUs); override any field on the
# command line (STEPS=..., EPISODES=..., EVAL_EPISODES=..., or edit the lerobot-train line).
# Paper scale: configs/pusht/pacdp_paper.json.
set -euo pipefail
cd "$(dirname "$0")/.."
source="${1:?usage: $0 PATH/TO/pusht_cchi_v7_replay.zarr|lerobot/pusht_keypoints [OUTPUT_DIR]}"
out="${2:-outputs/pusht_pacdp}"
episodes="${EPISODES:-0-205}"
bin=.venv/bin
[ -x "$bin/lerobot-train" ] || bin="$(dirname "$(command -v lerobot-train)")"

start=$(date +%s)  # epoch seconds: the summary script is another shell, whose $SECONDS starts at 0
if [ -e "$source" ]; then
  export HF_HUB_OFFLINE=1
  echo "== 1/3 converting PushT demos $episodes from $source"
  "$bin/pacdp-convert-pusht" --zarr="$source" --output_root="$out/data" --episodes="$episodes" --overwrite=true
  dataset=(--dataset.repo_id=local/pusht --dataset.root="$out/data")
else
  echo "== 1/3 using hub dataset $source, demos $episodes"
  episode_list=$("$bin/python" -c "from lerobot_pacdp.episodes import parse_episodes as p; import sys; print(str(p(sys.argv[1])).replace(' ', ''))" "$episodes")
  dataset=(--dataset.repo_id="$source" --dataset.episodes="$episode_list")
fi

echo "== 2/3 training PAC-DP with lerobot-train (configs/pusht/pacdp_cpu.json${STEPS:+, $STEPS steps}; 10% of the demos held out)"
rm -rf "$out/train"
"$bin/lerobot-train" --config_path=configs/pusht/pacdp_cpu.json "${dataset[@]}" ${STEPS:+--steps="$STEPS"} \
  --output_dir="$out/train" --wandb.enable=false

echo "== 3/3 evaluating the last checkpoint in gym-pusht"
bash examples/evaluate_and_summarize.sh "$out/train/checkpoints/last/pretrained_model" "$out" pusht "$start" -- \
  --env.type=pusht --env.obs_type=environment_state_agent_pos
