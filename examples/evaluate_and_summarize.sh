#!/usr/bin/env bash
# Roll a checkpoint out with lerobot-eval, measure its held-out NPE with pacdp-metrics, and write the run's
# summary (success rate with its 95% interval, NPE, steps, wall time) with pacdp-summarize-run.
#
#   bash examples/evaluate_and_summarize.sh CHECKPOINT OUTPUT_DIR TASK START_EPOCH_SECONDS -- <lerobot-eval --env.* flags>
#
# Knobs: EVAL_EPISODES (rollouts, default 50, distinct seeds), EVAL_BATCH (envs stepped together, default 1:
# LeRobot steps every env of a batch until the slowest one ends, so on a CPU one failed 400-step episode
# would hold up the whole batch; larger batches pay off only where a policy step is expensive, e.g. on a GPU).
set -euo pipefail
checkpoint="$1" out="$2" task="$3" start="$4"
shift 4
[ "${1:-}" = "--" ] && shift
bin="$(dirname "$0")/../.venv/bin"
[ -x "$bin/lerobot-eval" ] || bin="$(dirname "$(command -v lerobot-eval)")"
eval_episodes="${EVAL_EPISODES:-50}"
eval_batch="${EVAL_BATCH:-1}"

echo "== rolling out $checkpoint: $eval_episodes episodes, $eval_batch at a time (the first 10 are recorded as videos)"
rm -rf "$out/eval" "$out/metrics"
"$bin/lerobot-eval" --policy.path="$checkpoint" "$@" \
  --eval.n_episodes="$eval_episodes" --eval.batch_size="$eval_batch" --eval.use_async_envs=false \
  --output_dir="$out/eval"

echo "== held-out noise-prediction error of the checkpoint (pacdp-metrics, the run's held-out demos)"
"$bin/pacdp-metrics" --runs="[$checkpoint]" --nll=false --output_dir="$out/metrics" > "$out/metrics.log" 2>&1 \
  || { cat "$out/metrics.log"; exit 1; }

"$bin/pacdp-summarize-run" --eval_info="$out/eval/eval_info.json" --checkpoint="$checkpoint" \
  --metrics="$out/metrics/metrics.json" --task="$task" --wall_time_s="$(( $(date +%s) - start ))" --output="$out/summary.json"
videos=$(ls "$out"/eval/videos/*/*.mp4 "$out"/eval/videos/*.mp4 2>/dev/null | head -3 || true)
if [ -n "$videos" ]; then
  echo "rollout videos: $out/eval/videos/ (e.g. $(echo "$videos" | head -1))"
fi
