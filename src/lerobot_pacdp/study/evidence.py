"""The evidence table of a study: one row per run's final checkpoint, and paired PAC-DP vs DP tests.

`summary.json` is the list of rows {task, demos, method, seed, step, success_rate, n_episodes, heldout_npe}
(plus the success interval, the score `avg_max_reward` (on PushT Diffusion Policy's coverage score; None where
the rollouts predate it) and the NLL bound, valid and paper-compatible, in bits/dim). The paired test
matches PAC-DP and DP runs of the same task, demo count and seed (the same training and held-out demos,
the same rollout seeds) and asks whether the per-pair differences are centred on zero: an exact two-sided
sign-flip permutation test over all 2^pairs sign patterns, which assumes nothing about their distribution.
"""

import itertools
import math
import statistics
from collections import defaultdict
from dataclasses import dataclass

from lerobot_pacdp.rollout_summary import wilson_interval

METHODS = ("DP", "BDP", "PAC-DP")
PAIRED_METRICS = {"success_rate": True, "heldout_npe": False}  # metric: higher is better


@dataclass(frozen=True)
class PairedComparison:
    """PAC-DP minus DP on one metric of one task, over runs paired by (demos, seed)."""

    task: str
    metric: str
    pairs: int
    mean_difference: float  # PAC-DP - DP
    pacdp_better: int  # pairs where PAC-DP is better (higher success, lower NPE)
    ties: int
    dp_better: int
    p_value: float  # exact two-sided sign-flip permutation test


def at_reference_point(row: dict, references: dict[str, tuple[float, float]]) -> bool:
    """DP, or BDP / PAC-DP at the task's reference rho (and, for PAC-DP, its reference lambda)."""
    kl, rho = references[row["task"]]
    if row["method"] == "DP":
        return True
    expected_kl = 0.0 if row["method"] == "BDP" else kl
    return row["method"] in METHODS and row["prior_rho"] == rho and row["kl_weight"] == expected_kl


def final_rows(rows: list[dict], n_episodes: int, references: dict[str, tuple[float, float]]) -> list[dict]:
    """One row per run (its last checkpoint) of DP, BDP and PAC-DP at each task's reference point, sorted."""
    last: dict[str, dict] = {}
    for row in rows:
        if at_reference_point(row, references) and (row["run"] not in last or row["step"] > last[row["run"]]["step"]):
            last[row["run"]] = row
    result = []
    for row in last.values():
        rate = row.get("success_rate")
        successes = None if rate is None else round(rate * n_episodes)
        result.append({
            "task": row["task"], "demos": row["demos"], "method": row["method"], "seed": row["seed"],
            "step": row["step"], "success_rate": rate, "n_episodes": n_episodes if rate is not None else 0,
            "successes": successes, "avg_max_reward": row.get("avg_max_reward"),
            "ci95": list(wilson_interval(successes, n_episodes)) if successes is not None else None,
            "heldout_npe": row.get("npe"), "nll_bound_bits": row.get("nll_bound_bits"),
            "nll_paper_compatible_bits": row.get("nll_paper_compatible_bits"),
            "kl_weight": row["kl_weight"], "prior_rho": row["prior_rho"],
        })  # fmt: skip
    order = {m: i for i, m in enumerate(METHODS)}
    return sorted(result, key=lambda r: (r["task"], r["demos"], order[r["method"]], r["seed"]))


def sign_flip_p_value(differences: list[float]) -> float:
    """P(|mean of randomly signed differences| >= |observed mean|), exactly, over all sign patterns."""
    if not differences:
        return math.nan
    observed = abs(sum(differences))
    patterns = list(itertools.product((1, -1), repeat=len(differences)))
    extreme = sum(abs(sum(s * d for s, d in zip(signs, differences, strict=True))) >= observed - 1e-12
                  for signs in patterns)  # fmt: skip
    return extreme / len(patterns)


def paired_comparisons(summary: list[dict]) -> list[PairedComparison]:
    """PAC-DP vs DP per task and metric, pairing runs with the same demos and seed."""
    by_task: dict[str, dict[tuple, dict[str, dict]]] = defaultdict(lambda: defaultdict(dict))
    for row in summary:
        by_task[row["task"]][(row["demos"], row["seed"])][row["method"]] = row
    result = []
    for task, cells in by_task.items():
        for metric, higher_is_better in PAIRED_METRICS.items():
            diffs = [c["PAC-DP"][metric] - c["DP"][metric] for c in cells.values()
                     if "PAC-DP" in c and "DP" in c and None not in (c["PAC-DP"][metric], c["DP"][metric])]  # fmt: skip
            if not diffs:
                continue
            better = sum(d > 0 if higher_is_better else d < 0 for d in diffs)
            ties = sum(d == 0 for d in diffs)
            result.append(PairedComparison(task, metric, len(diffs), statistics.fmean(diffs), better, ties,
                                           len(diffs) - better - ties, sign_flip_p_value(diffs)))  # fmt: skip
    return result


def mean_spread(mean: float, std: float, n: int, digits: int) -> str:
    """"mean ± std" over n seeds (or grid points); one has no spread to show, so it is the value alone."""
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if n > 1 else "")


def _cell(values: list[float], digits: int) -> str:
    if not values:
        return "--"
    std = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{mean_spread(statistics.fmean(values), std, len(values), digits)} (n={len(values)})"


def render_evidence(summary: list[dict], comparisons: list[PairedComparison]) -> str:
    """The paper-shaped table (mean ± std over seeds of the final checkpoints) and the paired tests."""
    lines = ["## Final checkpoints: success rate and held-out NPE, mean ± std over seeds", "",
             "| task | demos | method | success rate | score (avg max reward) | held-out NPE | NLL bound (bits/dim) "
             "| paper-compatible NLL, not a bound (bits/dim) | runs (successes / rollouts) |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in summary:
        groups[(row["task"], row["demos"], row["method"])].append(row)
    for (task, demos, method), rows in groups.items():
        rates = [r["success_rate"] for r in rows if r["success_rate"] is not None]
        scores = [r["avg_max_reward"] for r in rows if r["avg_max_reward"] is not None]
        npes = [r["heldout_npe"] for r in rows if r["heldout_npe"] is not None]
        nlls = [r["nll_bound_bits"] for r in rows if r["nll_bound_bits"] is not None]
        papers = [r["nll_paper_compatible_bits"] for r in rows if r["nll_paper_compatible_bits"] is not None]
        counts = ", ".join(f"s{r['seed']}: {r['successes']}/{r['n_episodes']}" for r in rows if r["successes"] is not None)
        lines.append(f"| {task} | {demos} | {method} | {_cell(rates, 3)} | {_cell(scores, 3)} | {_cell(npes, 4)} "
                     f"| {_cell(nlls, 3)} | {_cell(papers, 3)} | {counts} |")  # fmt: skip
    lines += ["", "## PAC-DP vs DP, paired by (demos, seed): exact two-sided sign-flip test", ""]
    if not comparisons:  # e.g. a study of PAC-DP alone (--methods)
        return "\n".join([*lines, "No (demos, seed) has both a PAC-DP and a DP run: nothing to pair."]) + "\n"
    lines += ["| task | metric | pairs | mean PAC-DP − DP | PAC-DP better / tie / DP better | p |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for c in comparisons:
        lines.append(f"| {c.task} | {c.metric} | {c.pairs} | {c.mean_difference:+.4f} | "
                     f"{c.pacdp_better} / {c.ties} / {c.dp_better} | {c.p_value:.3f} |")  # fmt: skip
    return "\n".join(lines) + "\n"
