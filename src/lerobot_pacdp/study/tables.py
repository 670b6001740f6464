"""Tables I-III, Fig. 3-style plots, the training-dynamics and performance tables of a study.

The rows come from `lerobot_pacdp.study.evaluation` (one per checkpoint: NPE, NLL bound, success rate
and the run's spec). Per run, a metric is the mean over its last `last_k` checkpoints (`sweep.summarize`);
a cell is mean +- std (ddof=1) over seeds.

- Table I: per task at its largest demo count: DP, BDP (reference rho), PAC-DP (reference lambda, rho).
- Table II: per task x demos: DP, BDP best over rho, PAC-DP best over the lambda x rho grid.
- Table III: per task x demos: BDP average over rho, PAC-DP average over the grid (+- std over grid
  points of the seed means), PAC-DP best (+- std over seeds).
Tables II and III are written for each metric (the paper shows the success rate).
- Evidence (`study.evidence`): `summary.json`, one row per run's final checkpoint at the reference point,
  `paired.json` (PAC-DP vs DP per task, paired by demos and seed) and `evidence.md`.
"""

import csv
import io
import json
import logging
import math
import statistics
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.metrics.sweep import plot_metrics, summarize
from lerobot_pacdp.study.evaluation import SPEC_FIELDS
from lerobot_pacdp.study.evidence import (
    at_reference_point,
    final_rows,
    mean_spread,
    paired_comparisons,
    render_evidence,
)
from lerobot_pacdp.study.plan import RunSpec
from lerobot_pacdp.study.presets import Preset
from lerobot_pacdp.study.state import run_state

logger = logging.getLogger("pacdp-study")

METRICS = {"npe": "NPE", "nll_bound": "NLL bound", "success_rate": "SR"}
HIGHER_IS_BETTER = {"npe": False, "nll_bound": False, "success_rate": True}
PERFORMANCE_DIR = "performance"  # under the study's output dir: the speed benchmark's JSON per row


# ---------------------------------------------------------------------------------------------- per run


def per_run_values(rows: list[dict], last_k: int) -> list[dict]:
    """Per run: its spec and each metric's mean over its last `last_k` checkpoints (`sweep.summarize`)."""
    by_run: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        by_run[row["run"]].append(row)
    result = []
    for run_rows in by_run.values():
        summary = summarize([r | {"label": "run"} for r in run_rows], last_k)["run"]
        first = run_rows[0]
        entry = {k: first[k] for k in SPEC_FIELDS}
        entry["last_step"] = max(r["step"] for r in run_rows)
        entry.update({m: summary[m]["mean"] if m in summary else None for m in METRICS})
        result.append(entry)
    return result


# ----------------------------------------------------------------------------------------------- tables


def _mean_std(values: list[float]) -> tuple[float, float, int]:
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0, len(values)


def seed_statistics(per_run: list[dict]) -> dict[tuple, dict[str, tuple[float, float, int]]]:
    """{(task, demos, method, kl_weight, prior_rho): {metric: (mean, std over seeds, seeds)}}."""
    grouped: dict[tuple, list[dict]] = defaultdict(list)
    for run in per_run:
        grouped[(run["task"], run["demos"], run["method"], run["kl_weight"], run["prior_rho"])].append(run)
    stats = {}
    for key, runs in grouped.items():
        stats[key] = {}
        for metric in METRICS:
            values = [r[metric] for r in runs if r[metric] is not None and math.isfinite(r[metric])]
            if values:
                stats[key][metric] = _mean_std(values)
    return stats


def _best(points: dict[tuple, dict], metric: str) -> tuple[tuple, tuple[float, float, int]] | None:
    scored = [(key, s[metric]) for key, s in points.items() if metric in s]
    if not scored:
        return None
    pick = max if HIGHER_IS_BETTER[metric] else min
    return pick(scored, key=lambda item: item[1][0])


def build_tables(stats: dict, references: dict[str, tuple[float, float]]) -> list[dict]:
    """All table cells in long form: {table, task, demos, column, metric, mean, std, n, kl_weight, prior_rho}.

    `references[task] = (lambda, rho)`: the Table I / Fig. 3 point of PAC-DP (and BDP's rho).
    """
    cells = []

    def cell(table, task, demos, column, metric, value, kl=None, rho=None, n=None):
        mean, std, count = value
        cells.append({"table": table, "task": task, "demos": demos, "column": column, "metric": metric,
                      "mean": mean, "std": std, "n": n if n is not None else count, "kl_weight": kl, "prior_rho": rho})  # fmt: skip

    tasks = list(dict.fromkeys(key[0] for key in stats))
    for task in tasks:
        ref_kl, ref_rho = references[task]
        demos_list = sorted({key[1] for key in stats if key[0] == task})
        for demos in demos_list:
            dp = {k: v for k, v in stats.items() if k[:3] == (task, demos, "DP")}
            bdp = {k: v for k, v in stats.items() if k[:3] == (task, demos, "BDP")}
            pac = {k: v for k, v in stats.items() if k[:3] == (task, demos, "PAC-DP")}
            for metric in METRICS:
                if demos == demos_list[-1]:  # Table I: the largest demo count, reference points
                    for column, key in (("DP", (task, demos, "DP", None, None)), ("BDP", (task, demos, "BDP", 0.0, ref_rho)),
                                        ("PAC-DP", (task, demos, "PAC-DP", ref_kl, ref_rho))):  # fmt: skip
                        if metric in stats.get(key, {}):
                            cell("I", task, demos, column, metric, stats[key][metric], key[3], key[4])
                for column, points in (("DP", dp), ("BDP", bdp), ("PAC-DP", pac)):  # Table II: best of each
                    best = _best(points, metric)
                    if best:
                        cell("II", task, demos, column, metric, best[1], best[0][3], best[0][4])
                for column, points in (("BDP avg", bdp), ("PAC-DP avg", pac)):  # Table III
                    means = [s[metric][0] for s in points.values() if metric in s]
                    if means:
                        mean, std, _ = _mean_std(means)
                        cell("III", task, demos, column, metric, (mean, std, len(means)))
                best = _best(pac, metric)
                if best:
                    cell("III", task, demos, "PAC-DP best", metric, best[1], best[0][3], best[0][4])
    return cells


def _fmt(cell: dict | None, digits: int = 3) -> str:
    return "--" if cell is None else mean_spread(cell["mean"], cell["std"], cell["n"], digits)


def render_markdown(cells: list[dict], last_k: int) -> str:
    index = {(c["table"], c["task"], c["demos"], c["column"], c["metric"]): c for c in cells}
    tasks = list(dict.fromkeys(c["task"] for c in cells))
    out = [f"Per run: mean over its last {last_k} checkpoints; cells: mean ± std over seeds (n = seeds; the value alone where n = 1) unless noted.", ""]
    out += ["## Table I: generalization at the largest demo count (reference lambda, rho)", ""]
    header = ["Task", "demos"] + [f"{METRICS[m]} {c}" for m in METRICS for c in ("DP", "BDP", "PAC-DP")]
    out += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for task in tasks:
        table1 = [c for c in cells if c["table"] == "I" and c["task"] == task]
        if table1:
            demos = table1[0]["demos"]
            row = [task, str(demos)] + [_fmt(index.get(("I", task, demos, c, m))) for m in METRICS for c in ("DP", "BDP", "PAC-DP")]
            out.append("| " + " | ".join(row) + " |")
    for metric in METRICS:
        if not any(c["metric"] == metric and c["table"] == "II" for c in cells):
            continue
        demos_all = sorted({c["demos"] for c in cells if c["table"] == "II" and c["metric"] == metric})
        out += ["", f"## Table II ({METRICS[metric]}): DP, BDP best over rho, PAC-DP best over the grid", ""]
        header = ["Task"] + [f"{d} demos {c}" for d in demos_all for c in ("DP", "BDP", "PAC-DP")]
        out += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for task in tasks:
            out.append("| " + " | ".join([task] + [_fmt(index.get(("II", task, d, c, metric))) for d in demos_all
                                                    for c in ("DP", "BDP", "PAC-DP")]) + " |")  # fmt: skip
        out += ["", f"## Table III ({METRICS[metric]}): averages over the grid (± std over grid points) and the best point", ""]
        header = ["Task", "demos", "BDP avg", "PAC-DP avg", "PAC-DP best", "best (lambda, rho)"]
        out += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for task in tasks:
            for d in demos_all:
                best = index.get(("III", task, d, "PAC-DP best", metric))
                if best is None:
                    continue
                where = f"({best['kl_weight']:g}, {best['prior_rho']:g})"
                out.append("| " + " | ".join([task, str(d), _fmt(index.get(("III", task, d, "BDP avg", metric))),
                                              _fmt(index.get(("III", task, d, "PAC-DP avg", metric))), _fmt(best), where]) + " |")  # fmt: skip
    return "\n".join(out) + "\n"


def _csv(rows: list[dict]) -> str:
    if not rows:
        return ""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return buffer.getvalue()


def plot_reference_curves(rows: list[dict], references: dict, figures_dir: Path) -> None:
    """Fig. 3-style curves per (group, task, demos): DP, BDP and PAC-DP at the reference point."""
    panels: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        if at_reference_point(row, references):
            panels[(row["group"], row["task"], row["demos"])].append(row | {"label": row["method"]})
    for (group, task, demos), panel_rows in panels.items():
        directory = figures_dir / f"{group}_{task}_d{demos:03d}"
        directory.mkdir(parents=True, exist_ok=True)
        plot_metrics(panel_rows, directory)


# ------------------------------------------------------------------------------------ training dynamics


def dynamics_rows(rows: list[dict]) -> list[dict]:
    """Per run: where its held-out NPE was lowest, how far it rose after that, and its final NLL bound and KL.

    The question of the long runs: does DP overfit (NPE turns up after its best step) and does the
    KL term keep PAC-DP from doing so where BDP does not (paper Sec. IV, Fig. 3)."""
    by_run: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        if row.get("npe") is not None and math.isfinite(row["npe"]):
            by_run[row["run"]].append(row)
    result = []
    for run_rows in by_run.values():
        run_rows.sort(key=lambda r: r["step"])
        best, last = min(run_rows, key=lambda r: r["npe"]), run_rows[-1]
        result.append({
            "task": last["task"], "run": last["name"], "method": last["method"], "demos": last["demos"],
            "seed": last["seed"],
            "best_step": best["step"], "best_npe": best["npe"], "last_step": last["step"], "last_npe": last["npe"],
            "npe_rise": last["npe"] / best["npe"] - 1.0, "last_nll_bound": last.get("nll_bound"),
            "last_kl": last.get("kl"),
        })  # fmt: skip
    return result


def render_dynamics(dynamics: list[dict]) -> str:
    def num(value, digits: int) -> str:
        return "--" if value is None else f"{value:.{digits}g}"

    lines = ["## Training dynamics: best held-out NPE and what followed it (one row per run)", "",
             "| task | run | method | best NPE | at step | last step | NPE there | rise after best | NLL bound there | KL(Q‖P) there |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for d in dynamics:
        lines.append(f"| {d['task']} | {d['run']} | {d['method']} | {d['best_npe']:.4f} | {d['best_step']} | "
                     f"{d['last_step']} | {d['last_npe']:.4f} | {d['npe_rise']:+.1%} | {num(d['last_nll_bound'], 4)} | {num(d['last_kl'], 4)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ performance


def performance_table(preset: Preset, results_dir: Path, measure: bool) -> str:
    """PAC-DP / DP ratios from the speed benchmark's JSON in `results_dir` (measured first when `measure`)."""
    import torch

    from lerobot_pacdp.speed_benchmark import BenchmarkRequest, run_benchmark

    device = "cuda" if torch.cuda.is_available() else "cpu"
    lines = ["| U-Net preset | batch | device | train step | mean-mode chunk | sample-mode chunk | peak memory |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for row in preset.perf_rows:
        request = BenchmarkRequest(preset=row.speed_preset, device=device, output_dir=results_dir,
                                   batch_size=row.batch_size, train_steps=row.train_steps,
                                   latency_calls=row.latency_calls)  # fmt: skip
        if measure:
            logger.info("performance: %s", request)
            run_benchmark(request)
        if not request.result_file().is_file():
            lines.append(f"| {row.speed_preset} | {row.batch_size} | {device} | not measured (`pacdp-study --perf=true`) | | | |")
            continue
        result = json.loads(request.result_file().read_text())
        r = result["ratios_pacdp_over_dp"]
        dims = "/".join(map(str, result["config"]["down_dims"]))
        lines.append(f"| {row.speed_preset} ({dims}) | {row.batch_size} | {result['device']} | {r['train_step']:.2f} | "
                     f"{r['mean_mode_latency']:.2f} | {r['sample_mode_latency']:.2f} | {r['peak_memory']:.2f} |")  # fmt: skip
    return "## Performance: PAC-DP / DP ratios, each row measured in one run (DDIM 10, one action chunk)\n\n" + "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- report


def report(
    preset: Preset, specs: list[RunSpec], rows: list[dict], output_dir: Path, long_pair: bool = False,
    perf: bool = False,
) -> None:
    """Tables, CSVs and plots of `rows` (`evaluation.evaluate_runs`) under `output_dir/results[_long]`."""
    results = output_dir / ("results_long" if long_pair else "results")
    reported = {(r["group"], r["task"], r["name"]) for r in rows}
    if len(reported) < len(specs):
        logger.warning("tables cover %d of %d runs: the others are not finished yet.", len(reported), len(specs))
    short = [s.name for s in specs
             if (s.group, s.task, s.name) in reported and run_state(s, output_dir).status == "resume"]  # fmt: skip
    if short:
        logger.warning("reported before their last step (see last_step in runs.csv and the dynamics table): %s", short)
    if not rows:
        logger.warning("no finished run yet: no tables.")
        return
    references = {t.name: (t.reference_kl_weight, preset.reference_rho) for t in preset.tasks}
    per_run = per_run_values(rows, preset.last_k)
    cells = build_tables(seed_statistics(per_run), references)
    dynamics = dynamics_rows(rows)
    performance = performance_table(preset, output_dir / PERFORMANCE_DIR, perf)
    markdown = "\n".join([render_markdown(cells, preset.last_k), render_dynamics(dynamics), performance])
    write_text_atomic(results / "runs.csv", _csv(per_run))
    write_text_atomic(results / "dynamics.csv", _csv(dynamics))
    write_text_atomic(results / "tables.csv", _csv(cells))
    write_text_atomic(results / "tables.md", markdown)
    summary = final_rows(rows, preset.success_episodes, references)
    comparisons = paired_comparisons(summary)
    write_text_atomic(results / "summary.json", json.dumps(summary, indent=1) + "\n")
    write_text_atomic(results / "paired.json", json.dumps([asdict(c) for c in comparisons], indent=1) + "\n")
    write_text_atomic(results / "evidence.md", render_evidence(summary, comparisons))
    plot_reference_curves(rows, references, results / "figures")
    logger.info("wrote %s (tables.md, evidence.md, summary.json, paired.json, tables.csv, runs.csv, dynamics.csv, "
                "figures/)\n%s", results, markdown + render_evidence(summary, comparisons))
