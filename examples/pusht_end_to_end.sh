#!/usr/bin/env bash
# PushT with PAC-DP, end to end, offline: convert the demos, train with lerobot-train, roll out with lerobot-eval.
#
#   bash examples/pusht_end_to_end.sh PATH/TO/pusht_cchi_v7_replay.zarr [OUTPUT_DIR]
#
# The zarr is Diffusion Policy's PushT replay buffer (206 human demos). With the hub reachable you can
# skip the conversion and train on --dataset.repo_id=lerobot/pusht_keypoints instead.
# Sizes come from configs/pusht/pacdp_cpu.json (a small U-Net for CPUs); override any field on the
# command line (STEPS=..., EPISODES=..., or edit the lerobot-train line). Paper scale: configs/pusht/pacdp_paper.json.
set -euo pipefail
zarr="${1:?usage: $0 PATH/TO/pusht_cchi_v7_replay.zarr [OUTPUT_DIR]}"
out="${2:-outputs/pusht_pacdp}"
steps="${STEPS:-2000}"
episodes="${EPISODES:-0-39}"
eval_episodes="${EVAL_EPISODES:-10}"
bin="$(dirname "$0")/../.venv/bin"
[ -x "$bin/lerobot-train" ] || bin="$(dirname "$(command -v lerobot-train)")"
export HF_HUB_OFFLINE=1

echo "== 1/3 converting PushT demos $episodes from $zarr"
"$bin/pacdp-convert-pusht" --zarr "$zarr" --output-root "$out/data" --episodes "$episodes" --overwrite

echo "== 2/3 training PAC-DP for $steps steps (10% of the demos held out for the NPE)"
rm -rf "$out/train"
"$bin/lerobot-train" --config_path=configs/pusht/pacdp_cpu.json \
  --dataset.repo_id=local/pusht --dataset.root="$out/data" \
  --steps="$steps" --output_dir="$out/train" --wandb.enable=false

echo "== 3/3 rolling out the last checkpoint in gym-pusht ($eval_episodes episodes)"
rm -rf "$out/eval"
"$bin/lerobot-eval" --policy.path="$out/train/checkpoints/last/pretrained_model" \
  --env.type=pusht --env.obs_type=environment_state_agent_pos \
  --eval.n_episodes="$eval_episodes" --eval.batch_size=5 --eval.use_async_envs=false \
  --output_dir="$out/eval"
python3 - "$out" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
overall = json.loads((out / "eval" / "eval_info.json").read_text())["overall"]
print(f"success rate: {overall['pc_success']:.1f}% over {overall['n_episodes']} episodes  (videos: {out / 'eval' / 'videos'})")
PY
