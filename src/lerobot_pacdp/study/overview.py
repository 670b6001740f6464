"""Several evidence studies at a glance: one row per (task, demos, budget), against the paper's Table II.

Each study directory holds a `summary.json` (`study.evidence`: one row per run's final checkpoint). A row
here is a (task, demos, final step) over every study given; its cells are mean ± std (ddof=1) over seeds of
the final success rate, PAC-DP minus DP paired by seed, and the held-out NPE of DP and PAC-DP. A row with
fewer seeds than the study's protocol says which seeds it has and gives no verdict.

    python -m lerobot_pacdp.study.overview results/study_cpu_v2*   # the README's at-a-glance table
    python -m lerobot_pacdp.study.overview results/study_cpu_v2* --budget_plot=budgets.png   # and the plot

The plot shows each method's final success against the budget, per (task, demos): where success stops
changing with more steps (each budget is its own set of runs, its cosine decay spanning it), including
budgets only some methods or seeds were trained at.
"""

import argparse
import json
import statistics
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lerobot_pacdp.study.evidence import METHODS, mean_spread
from lerobot_pacdp.study.presets import PAPER_SEEDS

# Table II of the paper, success rate of DP / BDP / PAC-DP, by (task, training demos).
PAPER_TABLE_II = {
    ("pusht", 20): (0.481, 0.495, 0.549), ("pusht", 40): (0.532, 0.552, 0.608),
    ("lift", 20): (0.972, 0.990, 0.996), ("lift", 40): (0.991, 0.994, 0.997),
    ("can", 20): (0.781, 0.865, 0.906), ("can", 40): (0.923, 0.925, 0.964),
    ("square", 20): (0.470, 0.474, 0.500), ("square", 40): (0.701, 0.700, 0.686),
}  # fmt: skip
TASK_NAMES = {"can": "Can", "lift": "Lift", "pusht": "PushT", "square": "Square"}  # also the rows' order
TIE = 0.02  # one rollout of 50: a smaller mean difference in success is a tie


@dataclass(frozen=True)
class BudgetPoint:
    """One method's final success at one budget of a (task, demos): mean and std (ddof=1) over its seeds."""

    steps: int
    mean: float
    std: float
    seeds: tuple[int, ...]


@dataclass(frozen=True)
class OverviewRow:
    """The final checkpoints of one (task, demos, budget), per method: success rates and NPEs by seed."""

    task: str
    demos: int
    steps: int
    success: dict[str, dict[int, float]]  # method -> seed -> success rate
    npe: dict[str, dict[int, float]]

    @property
    def seeds(self) -> tuple[int, ...]:
        """The seeds every method has."""
        common = set.intersection(*(set(self.success.get(m, {})) for m in METHODS))
        return tuple(sorted(common))


def overview_rows(study_dirs: Sequence[Path]) -> list[OverviewRow]:
    """The rows of every study's summary.json; one (task, demos, steps) may come from one study only."""
    return [row for row in _all_rows(study_dirs) if row.seeds]  # no seed finished by every method: no row yet


def budget_points(study_dirs: Sequence[Path]) -> dict[tuple[str, int], dict[str, list[BudgetPoint]]]:
    """Per (task, demos) and method, its final success at each budget over the seeds it has there."""
    points: dict[tuple[str, int], dict[str, list[BudgetPoint]]] = defaultdict(lambda: defaultdict(list))
    for row in _all_rows(study_dirs):
        for method in METHODS:
            by_seed = row.success.get(method, {})
            if by_seed:
                values = [by_seed[s] for s in sorted(by_seed)]
                std = statistics.stdev(values) if len(values) > 1 else 0.0
                point = BudgetPoint(row.steps, statistics.fmean(values), std, tuple(sorted(by_seed)))
                points[(row.task, row.demos)][method].append(point)
    return {key: dict(methods) for key, methods in points.items()}


def plot_budgets(points: dict[tuple[str, int], dict[str, list[BudgetPoint]]], path: Path) -> None:
    """One panel per (task, demos): final success against training steps per method, mean ± std over seeds;
    a point with fewer seeds than the protocol is hollow and names its seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(points), figsize=(4 * len(points), 3.6), squeeze=False, sharey=True)
    for ax, ((task, demos), methods) in zip(axes[0], points.items(), strict=True):
        for i, method in enumerate(METHODS):
            line = sorted(methods.get(method, []), key=lambda p: p.steps)
            if not line:
                continue
            full = [p for p in line if len(p.seeds) >= len(PAPER_SEEDS)]  # one line through comparable means
            ax.errorbar([p.steps for p in full], [p.mean for p in full], yerr=[p.std for p in full], color=f"C{i}",
                        marker="o", capsize=3, label=method)  # fmt: skip
            for p in line:
                if len(p.seeds) < len(PAPER_SEEDS):
                    ax.plot(p.steps, p.mean, "o", color=f"C{i}", markerfacecolor="white", markersize=7)
                    ax.annotate(_seeds(p.seeds), (p.steps, p.mean), textcoords="offset points", xytext=(4, -12),
                                fontsize=7, color=f"C{i}")  # fmt: skip
        budgets = sorted({p.steps for line in methods.values() for p in line})
        ax.set_xscale("log", base=2)  # budgets from 3000 to 60000 steps, most of them doubling
        ax.set_xticks(budgets, [f"{b // 1000}k" if b % 1000 == 0 else str(b) for b in budgets])
        ax.minorticks_off()
        ax.set_xlim(budgets[0] / 1.3, budgets[-1] * 1.3)
        ax.set_title(f"{TASK_NAMES.get(task, task)}, {demos} demos")
        ax.set_xlabel("training steps (budget)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("final success rate")
    axes[0][0].legend(loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _all_rows(study_dirs: Sequence[Path]) -> list[OverviewRow]:
    """Every (task, demos, steps) of the studies, with whatever methods and seeds it has."""
    cells: dict[tuple[str, int, int], dict[str, dict]] = {}
    source: dict[tuple[str, int, int], Path] = {}
    for study in study_dirs:
        for row in json.loads((study / "summary.json").read_text()):
            if row["success_rate"] is None or row["heldout_npe"] is None:
                continue  # a run not rolled out (or measured) yet
            key = (row["task"], row["demos"], row["step"])
            if source.setdefault(key, study) != study:
                raise ValueError(f"{key} is in both {source[key]} and {study}: give each budget one study.")
            cell = cells.setdefault(key, {"success": defaultdict(dict), "npe": defaultdict(dict)})
            cell["success"][row["method"]][row["seed"]] = row["success_rate"]
            cell["npe"][row["method"]][row["seed"]] = row["heldout_npe"]
    order = list(TASK_NAMES)
    keys = sorted(cells, key=lambda k: (order.index(k[0]) if k[0] in order else len(order), k))
    return [OverviewRow(*key, dict(cells[key]["success"]), dict(cells[key]["npe"])) for key in keys]


def _mean(values: list[float], digits: int) -> str:
    std = statistics.stdev(values) if len(values) > 1 else 0.0
    return mean_spread(statistics.fmean(values), std, len(values), digits)


def _seeds(seeds: tuple[int, ...]) -> str:
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(map(str, seeds))


def render_row(row: OverviewRow, paper: tuple[float, float, float] | None) -> str:
    """A markdown row: success per method (best mean in bold), PAC-DP − DP, NPE DP → PAC-DP, the paper's."""
    seeds = row.seeds
    complete = len(seeds) >= len(PAPER_SEEDS)
    means = {m: statistics.fmean(row.success[m][s] for s in seeds) for m in METHODS}
    best = max(means.values())
    cells = []
    for method in METHODS:
        text = _mean([row.success[method][s] for s in seeds], 3)
        text = f"**{text}**" if means[method] == best else text
        cells.append(text if complete else f"{text} ({_seeds(seeds)} only)")
    differences = [row.success["PAC-DP"][s] - row.success["DP"][s] for s in seeds]
    difference = statistics.fmean(differences)
    better, level = sum(d > 0 for d in differences), sum(d == 0 for d in differences)
    counts = f"({better} / {level} / {len(differences) - better - level})"
    if not complete:
        verdict = f"{difference:+.3f} {counts}: {_seeds(seeds)} of {len(PAPER_SEEDS)}"
    elif abs(difference) < TIE:
        verdict = f"{difference:+.3f} {counts}: ties"
    else:
        shown = f"**{difference:+.3f}**" if difference > 0 else f"{difference:+.3f}"
        verdict = f"{shown} {counts}: {'wins' if difference > 0 else 'loses'}"
    npe = " → ".join(f"{statistics.fmean(row.npe[m][s] for s in seeds):.3f}" for m in ("DP", "PAC-DP"))
    table = " / ".join(f"{v:.3f}" for v in paper) + " " if paper else ""
    name = f"{TASK_NAMES.get(row.task, row.task)}, {row.demos}"
    return f"| {name} | {row.steps} | {' | '.join(cells)} | {verdict} | {npe} | {table}|"


def render_overview(rows: list[OverviewRow]) -> str:
    """The table; the paper's values stand on the first row of each (task, demos)."""
    lines = ["| task, training demos | steps | DP | BDP | PAC-DP "
             "| PAC-DP − DP (seeds better / level / worse) | held-out NPE, DP → PAC-DP "
             "| paper Table II, DP / BDP / PAC-DP |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    shown = set()
    for row in rows:
        key = (row.task, row.demos)
        lines.append(render_row(row, None if key in shown else PAPER_TABLE_II.get(key)))
        shown.add(key)
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("studies", nargs="+", type=Path, help="published studies (with summary.json)")
    parser.add_argument("--budget_plot", type=Path, help="also plot final success against the budget (PNG)")
    args = parser.parse_args(argv)
    missing = [str(s) for s in args.studies if not (s / "summary.json").is_file()]
    if missing:
        print(f"no summary.json in {', '.join(missing)}: give published study directories "
              "(benchmarks/study_cpu_v2.sh publish writes them).", file=sys.stderr)  # fmt: skip
        return 2
    try:
        print(render_overview(overview_rows(args.studies)), end="")
        if args.budget_plot is not None:
            plot_budgets(budget_points(args.studies), args.budget_plot)
    except ValueError as error:
        print(error, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
