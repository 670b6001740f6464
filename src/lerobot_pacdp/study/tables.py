"""Tables I-III, Fig. 3-style plots and the performance table of a study.

The metrics come from `lerobot_pacdp.metrics.sweep` (NPE and NLL bound on every checkpoint, on the
seed's held-out demos) plus the success rate of each run's last checkpoints (the sweep's
`success_rate`, LeRobot's own rollout loop). Per run, a metric is the mean over its last `last_k`
checkpoints (`sweep.summarize`); a cell is mean +- std (ddof=1) over seeds.

- Table I: per task at its largest demo count: DP, BDP (reference rho), PAC-DP (reference lambda, rho).
- Table II: per task x demos: DP, BDP best over rho, PAC-DP best over the lambda x rho grid.
- Table III: per task x demos: BDP average over rho, PAC-DP average over the grid (+- std over grid
  points of the seed means), PAC-DP best (+- std over seeds).
Tables II and III are written for each metric (the paper shows the success rate).
"""

import csv
import io
import json
import logging
import math
import statistics
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import draccus

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.metrics.checkpoints import list_checkpoints, load_policy
from lerobot_pacdp.metrics.sweep import SweepConfig, plot_metrics, run_sweep, success_rate, summarize
from lerobot_pacdp.study.presets import REPO_ROOT, Preset
from lerobot_pacdp.study.runner import RunSpec, run_status, write_json_atomic

logger = logging.getLogger("pacdp-study")

METRICS = {"npe": "NPE", "nll_bound": "NLL bound", "success_rate": "SR"}
HIGHER_IS_BETTER = {"npe": False, "nll_bound": False, "success_rate": True}
SPEED_SCRIPT = REPO_ROOT / "benchmarks" / "speed.py"
SPEED_RESULTS = REPO_ROOT / "benchmarks" / "results"


# ---------------------------------------------------------------------------------------------- metrics


def _spec_fields(spec: RunSpec) -> dict:
    return {"task": spec.task, "demos": spec.demos, "seed": spec.seed, "method": spec.method,
            "kl_weight": spec.kl_weight, "prior_rho": spec.prior_rho, "name": spec.name}  # fmt: skip


def evaluate_runs(preset: Preset, specs: list[RunSpec], output_dir: Path, unfinished: bool = False) -> list[dict]:
    """One row per checkpoint of every finished run (the sweep's columns plus the run's spec); with
    `unfinished`, also of runs stopped before their last step, up to their last checkpoint."""
    wanted = ("done", "resume") if unfinished else ("done",)
    groups: dict[tuple, list[RunSpec]] = defaultdict(list)
    for spec in specs:
        if run_status(spec, output_dir)[0] in wanted:
            groups[(spec.group, spec.task, spec.seed)].append(spec)
    rows = []
    for (group, task, seed), runs in groups.items():
        logger.info("metrics: %s/%s seed %d, %d runs on %d held-out demos", group, task, seed, len(runs),
                    len(runs[0].heldout_episodes))  # fmt: skip
        sweep = SweepConfig(
            runs=",".join(str(s.train_dir(output_dir)) for s in runs),
            labels=",".join(s.name for s in runs),
            output_dir=output_dir / "metrics" / group / task / f"seed{seed}",
            episodes=",".join(map(str, runs[0].heldout_episodes)),
            batch_size=preset.metrics_batch_size,
            nll_steps=preset.nll_steps,
            frame_stride=preset.frame_stride,
            last_k=preset.last_k,
            device=preset.device,
        )
        by_name = {s.name: s for s in runs}
        sweep_rows, _ = run_sweep(sweep)
        rows += [row | _spec_fields(by_name[row["label"]]) | {"group": group} for row in sweep_rows]
        if preset.success_episodes > 0:
            add_success_rates(preset, runs, rows, output_dir, output_dir / "metrics" / group / task / f"seed{seed}")
    return rows


def add_success_rates(preset: Preset, runs: list[RunSpec], rows: list[dict], output_dir: Path, cache_dir: Path) -> None:
    """Success rate of each run's last `success_last_k` checkpoints, cached in `success.json`."""
    from lerobot.envs.configs import EnvConfig

    task = preset.task(runs[0].task)
    env_dict = task.train_config["env"]
    settings = {"episodes": preset.success_episodes, "seed": 0, "env": env_dict}
    cache_file = cache_dir / "success.json"
    cache = json.loads(cache_file.read_text()) if cache_file.is_file() else {}
    rates = cache.get("rates", {}) if cache.get("settings") == settings else {}
    wanted = [c for s in runs for _, c in list_checkpoints(s.train_dir(output_dir))[-preset.success_last_k :]]
    todo = [c for c in wanted if str(c) not in rates]
    if todo:
        env_cfg = draccus.decode(EnvConfig, env_dict)
        n_envs = min(10, preset.success_episodes)
        for ckpt in todo:
            loaded = load_policy(ckpt, preset.device)
            rates[str(ckpt)] = success_rate(loaded, env_cfg, n_envs, preset.success_episodes, seed=0)
            logger.info("success rate %s: %.3f over %d rollouts", ckpt, rates[str(ckpt)], preset.success_episodes)
            write_json_atomic(cache_file, {"settings": settings, "rates": rates})
    for row in rows:
        if row["checkpoint"] in rates:
            row["success_rate"] = rates[row["checkpoint"]]


def per_run_values(rows: list[dict], last_k: int) -> list[dict]:
    """Per run: its spec and each metric's mean over its last `last_k` checkpoints (`sweep.summarize`)."""
    by_run: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        by_run[row["run"]].append(row)
    result = []
    for run_rows in by_run.values():
        summary = summarize([r | {"label": "run"} for r in run_rows], last_k)["run"]
        first = run_rows[0]
        entry = {k: first[k] for k in ("task", "demos", "seed", "method", "kl_weight", "prior_rho", "name", "group")}
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
    return "--" if cell is None else f"{cell['mean']:.{digits}f} ± {cell['std']:.{digits}f}"


def render_markdown(cells: list[dict], last_k: int) -> str:
    index = {(c["table"], c["task"], c["demos"], c["column"], c["metric"]): c for c in cells}
    tasks = list(dict.fromkeys(c["task"] for c in cells))
    out = [f"Per run: mean over its last {last_k} checkpoints; cells: mean ± std over seeds (n = seeds) unless noted.", ""]
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
        ref_kl, ref_rho = references[row["task"]]
        if row["method"] == "DP" or (row["prior_rho"] == ref_rho and row["kl_weight"] in (0.0, ref_kl)):
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
            "run": last["name"], "method": last["method"], "demos": last["demos"], "seed": last["seed"],
            "best_step": best["step"], "best_npe": best["npe"], "last_step": last["step"], "last_npe": last["npe"],
            "npe_rise": last["npe"] / best["npe"] - 1.0, "last_nll_bound": last.get("nll_bound"),
            "last_kl": last.get("kl"),
        })  # fmt: skip
    return result


def render_dynamics(dynamics: list[dict]) -> str:
    def num(value, digits: int) -> str:
        return "--" if value is None else f"{value:.{digits}g}"

    lines = ["## Training dynamics: best held-out NPE and what followed it (one row per run)", "",
             "| run | method | best NPE | at step | last step | NPE there | rise after best | NLL bound there | KL(Q‖P) there |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for d in dynamics:
        lines.append(f"| {d['run']} | {d['method']} | {d['best_npe']:.4f} | {d['best_step']} | {d['last_step']} | "
                     f"{d['last_npe']:.4f} | {d['npe_rise']:+.1%} | {num(d['last_nll_bound'], 4)} | {num(d['last_kl'], 4)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ performance


def performance_table(preset: Preset, measure: bool) -> str:
    """PAC-DP / DP ratios from `benchmarks/speed.py` results (measured first when `measure`)."""
    import torch

    device = "cuda" if torch.cuda.is_available() else "cpu"
    lines = ["| U-Net preset | batch | device | train step | mean-mode chunk | sample-mode chunk | peak memory |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for row in preset.perf_rows:
        speed_preset, batch = row.speed_preset, row.batch_size
        result_file = SPEED_RESULTS / f"speed_{speed_preset}_b{batch}_{device}.json"
        if measure:
            args = ["--preset", speed_preset, "--batch-size", str(batch), "--device", device, *row.extra_args]
            logger.info("performance: benchmarks/speed.py %s", " ".join(args))
            subprocess.run([sys.executable, str(SPEED_SCRIPT), *args], check=True)
        if not result_file.is_file():
            lines.append(f"| {speed_preset} | {batch} | {device} | not measured (`pacdp-study --perf=true`) | | | |")
            continue
        result = json.loads(result_file.read_text())
        r = result["ratios_pacdp_over_dp"]
        dims = "/".join(map(str, result["config"]["down_dims"]))
        lines.append(f"| {speed_preset} ({dims}) | {batch} | {result['device']} | {r['train_step']:.2f} | "
                     f"{r['mean_mode_latency']:.2f} | {r['sample_mode_latency']:.2f} | {r['peak_memory']:.2f} |")  # fmt: skip
    return "## Performance: PAC-DP / DP ratios, each row measured in one run (DDIM 10, one action chunk)\n\n" + "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- report


def report(
    preset: Preset, specs: list[RunSpec], output_dir: Path, long_pair: bool = False, perf: bool = False,
    unfinished: bool = False,
) -> None:
    """Metrics of every finished run (and unfinished ones with `unfinished`), then tables, CSVs and plots
    under `output_dir/results[_long]`."""
    rows = evaluate_runs(preset, specs, output_dir, unfinished)
    results = output_dir / ("results_long" if long_pair else "results")
    reported = {r["run"] for r in rows}
    if len(reported) < len(specs):
        logger.warning("tables cover %d of %d runs: the others are not finished yet.", len(reported), len(specs))
    short = [s.name for s in specs if str(s.train_dir(output_dir)) in reported and run_status(s, output_dir)[0] != "done"]
    if short:
        logger.warning("reported before their last step (see last_step in runs.csv and the dynamics table): %s", short)
    if not rows:
        logger.warning("no finished run yet: no tables.")
        return
    references = {t.name: (t.reference_kl_weight, preset.reference_rho) for t in preset.tasks}
    per_run = per_run_values(rows, preset.last_k)
    cells = build_tables(seed_statistics(per_run), references)
    dynamics = dynamics_rows(rows)
    markdown = "\n".join([render_markdown(cells, preset.last_k), render_dynamics(dynamics), performance_table(preset, perf)])
    write_text_atomic(results / "runs.csv", _csv(per_run))
    write_text_atomic(results / "dynamics.csv", _csv(dynamics))
    write_text_atomic(results / "tables.csv", _csv(cells))
    write_text_atomic(results / "tables.md", markdown)
    plot_reference_curves(rows, references, results / "figures")
    logger.info("wrote %s (tables.md, tables.csv, runs.csv, dynamics.csv, figures/)\n%s", results, markdown)
