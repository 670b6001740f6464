#!/usr/bin/env bash
# Issue 14's evidence study in pieces: `pacdp-study --preset=cpu_v2` for one task and one seed per call (6 runs
# of Lift or Can, DP twin / BDP / PAC-DP x 20 and 40 demos; 3 runs of PushT), each piece resumable, then the
# tables of everything finished so far, copied into results/study_cpu_v2 (commit them as each piece lands).
#
#   bash benchmarks/study_cpu_v2.sh lift 0        # train and evaluate Lift seed 0 (~1 h on 2 cores)
#   bash benchmarks/study_cpu_v2.sh lift 1 2      # seeds 1 and 2, one after the other
#   bash benchmarks/study_cpu_v2.sh publish       # only (re)write the tables of every finished piece
#
# The study records its 60 scripted Lift / Can demos itself (seed 0); PushT reads ../shared's replay buffer.
# OUT (default outputs/study_cpu_v2) is the study's output dir.
#
# A longer budget than the task's CPU recipe, as its own study (own output and results dirs):
#   STEPS=6000 SUCCESS_EVERY=2000 bash benchmarks/study_cpu_v2.sh lift 0 1 2
#   -> outputs/study_cpu_v2_steps6000, results/study_cpu_v2_steps6000 (checkpoints every 1000 steps)
# DEMOS=20 (or 40) trains only those runs of each piece; the tables always cover every finished run.
# METHODS=PAC-DP (or DP,BDP) trains and reports only those methods' runs (give it to the publish step too).
set -euo pipefail
cd "$(dirname "$0")/.."
suffix="${STEPS:+_steps$STEPS}"
out="${OUT:-outputs/study_cpu_v2$suffix}"
zarr=../shared/data/pusht/pusht_cchi_v7_replay.zarr
study=(.venv/bin/pacdp-study --preset=cpu_v2 --output_dir="$out" --pusht_zarr="$zarr"
       ${STEPS:+--steps="$STEPS" --save_freq=1000} ${SUCCESS_EVERY:+--success_every="$SUCCESS_EVERY"}
       ${METHODS:+--methods="[$METHODS]"})
export HF_HUB_OFFLINE=1
task="${1:?usage: $0 lift|can|pusht SEED... | publish}"
shift
if [ "$task" != publish ]; then
  for seed in "${@:?give one or more seeds (0 1 2)}"; do
    "${study[@]}" --tasks="[$task]" --seeds="[$seed]" ${DEMOS:+--demos="[$DEMOS]"}
  done
fi
# Tables over every piece trained so far (metrics and success rates are cached per task and seed; a piece
# trained with --metrics=false gets them here). Pieces already published from another checkout, whose runs
# are not under $out, keep their committed rows: --published_metrics merges them into the cache, run by run.
dest=results/study_cpu_v2$suffix
published=()
[ -d "$dest/metrics" ] && published=(--published_metrics="$dest/metrics")
tasks=$( { find "$out/runs" "$out/metrics/main" "$dest/metrics/main" -mindepth 1 -maxdepth 1 -type d -printf '%f\n' \
           2>/dev/null || true; } | sort -u | paste -sd, -)
[ -n "$tasks" ] || { echo "nothing finished yet under $out" >&2; exit 1; }
"${study[@]}" --tasks="[$tasks]" --train=false "${published[@]}"
rm -rf "$dest.tmp" && mkdir -p "$dest.tmp"
cp -r "$out/results/." "$dest.tmp/"
(cd "$out" && find metrics/main -name metrics.json -o -name success.json -o -name datasets.json) |
while read -r f; do
  mkdir -p "$dest.tmp/$(dirname "$f")" && cp "$out/$f" "$dest.tmp/$f"
done
[ -f "$dest/README.md" ] && cp "$dest/README.md" "$dest.tmp/"  # the hand-written notes stay
rm -rf "$dest" && mv "$dest.tmp" "$dest"
echo "tables of the finished pieces: $dest (evidence.md, summary.json, paired.json, tables.md, figures/)"
echo "the README's at-a-glance table (paste it over the old one: tests/study/test_overview.py compares them)"
echo "and its plot of final success against the budget, results/study_cpu_v2/figures/budgets.png:"
.venv/bin/python -m lerobot_pacdp.study.overview results/study_cpu_v2* --budget_plot=results/study_cpu_v2/figures/budgets.png
