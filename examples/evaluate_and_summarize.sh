#!/usr/bin/env bash
# Roll a checkpoint out with lerobot-eval, measure its held-out NPE with pacdp-metrics, and write the run's
# summary (success rate with its 95% interval, NPE, steps, wall time) with pacdp-summarize-run.
#
#   bash examples/evaluate_and_summarize.sh CHECKPOINT OUTPUT_DIR TASK START_EPOCH_SECONDS -- <lerobot-eval --env.* flags>
#
# Knobs: EVAL_EPISODES (rollouts, default 50, distinct seeds from EVAL_SEED, default 1000 as lerobot-eval's),
# EVAL_PROCS (lerobot-eval processes of one torch thread each, default 2: a batch-1 rollout is single-threaded, so
# two processes on two cores roll out about twice as fast; process k takes the k-th consecutive range of seeds and
# its output goes to OUTPUT_DIR/eval/partK, the first one's to the terminal), EVAL_BATCH (envs each process steps
# together, default 1: LeRobot steps every env of a batch until the slowest one ends, so on a CPU one failed
# 400-step episode would hold up the whole batch; larger batches pay off where a policy step is expensive, e.g. a GPU).
set -euo pipefail
checkpoint="$1" out="$2" task="$3" start="$4"
shift 4
[ "${1:-}" = "--" ] && shift
bin="$(dirname "$0")/../.venv/bin"
[ -x "$bin/lerobot-eval" ] || bin="$(dirname "$(command -v lerobot-eval)")"
eval_episodes="${EVAL_EPISODES:-50}"
eval_batch="${EVAL_BATCH:-1}"
eval_procs="${EVAL_PROCS:-2}"
eval_seed="${EVAL_SEED:-1000}"

echo "== rolling out $checkpoint: $eval_episodes episodes (seeds $eval_seed-$((eval_seed + eval_episodes - 1))) in" \
  "$eval_procs processes, $eval_batch env(s) at a time each (each process records its first 10 as videos)"
rm -rf "$out/eval" "$out/metrics"
mkdir -p "$out/eval"
per_proc=$(( (eval_episodes + eval_procs - 1) / eval_procs ))
infos=() pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true' EXIT  # no rollout outlives a failed job
for ((k = eval_procs - 1; k >= 0; k--)); do  # the first range last, in the foreground, so its progress shows
  first=$(( k * per_proc ))
  n=$(( eval_episodes - first < per_proc ? eval_episodes - first : per_proc ))
  [ "$n" -gt 0 ] || continue
  args=(--policy.path="$checkpoint" "$@" --seed=$(( eval_seed + first )) --eval.n_episodes="$n"
        --eval.batch_size=$(( eval_batch < n ? eval_batch : n )) --eval.use_async_envs=false --output_dir="$out/eval/part$k")
  infos=("$out/eval/part$k/eval_info.json" "${infos[@]}")
  if [ "$k" -gt 0 ]; then
    OMP_NUM_THREADS=1 "$bin/lerobot-eval" "${args[@]}" > "$out/eval/part$k.log" 2>&1 &
    pids+=($!)
  else
    OMP_NUM_THREADS=1 "$bin/lerobot-eval" "${args[@]}"
  fi
done
for pid in "${pids[@]}"; do
  wait "$pid" || { tail -n 30 "$out"/eval/part*.log; echo "a lerobot-eval process failed (logs: $out/eval/part*.log)" >&2; exit 1; }
done
eval_info_list=$(IFS=,; echo "${infos[*]}")

echo "== held-out noise-prediction error of the checkpoint (pacdp-metrics, the run's held-out demos)"
"$bin/pacdp-metrics" --runs="[$checkpoint]" --nll=false --output_dir="$out/metrics" > "$out/metrics.log" 2>&1 \
  || { cat "$out/metrics.log"; exit 1; }

"$bin/pacdp-summarize-run" --eval_info="[$eval_info_list]" --checkpoint="$checkpoint" \
  --metrics="$out/metrics/metrics.json" --task="$task" --wall_time_s="$(( $(date +%s) - start ))" --output="$out/summary.json"
videos=$(ls "$out"/eval/part*/videos/*/*.mp4 "$out"/eval/part*/videos/*.mp4 2>/dev/null | head -3 || true)
if [ -n "$videos" ]; then
  echo "rollout videos: $out/eval/part*/videos/ (e.g. $(echo "$videos" | head -1))"
fi
