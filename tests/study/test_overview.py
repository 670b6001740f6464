"""The at-a-glance table over several published studies (`lerobot_pacdp.study.overview`)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_pacdp.study import overview

from pacdp_testing import REPO_ROOT


def _study(directory: Path, task: str, demos: int, step: int, cells: dict[str, list[tuple[float, float]]]) -> Path:
    """A published study's summary.json: per method, (success rate, held-out NPE) for seeds 0, 1, ..."""
    rows = [{"task": task, "demos": demos, "method": method, "seed": seed, "step": step, "success_rate": rate,
             "n_episodes": 50, "heldout_npe": npe}
            for method, values in cells.items() for seed, (rate, npe) in enumerate(values)]  # fmt: skip
    directory.mkdir(parents=True)
    (directory / "summary.json").write_text(json.dumps(rows))
    return directory


def test_each_budget_is_a_row_with_seed_means_a_paired_verdict_and_the_papers_values_once(tmp_path):
    can = _study(tmp_path / "can", "can", 20, 100, {
        "DP": [(0.5, 0.2), (0.6, 0.3), (0.7, 0.4)],
        "BDP": [(0.4, 0.2), (0.4, 0.2), (0.4, 0.2)],
        "PAC-DP": [(0.7, 0.1), (0.6, 0.1), (0.8, 0.1)],
    })  # fmt: skip
    can_longer = _study(tmp_path / "can_longer", "can", 20, 200, {  # seed 1's BDP is not rolled out yet
        "DP": [(0.5, 0.3), (0.6, 0.3)], "BDP": [(0.52, 0.3), (None, 0.3)], "PAC-DP": [(0.48, 0.1), (0.7, 0.1)],
    })  # fmt: skip
    lift = _study(tmp_path / "lift", "lift", 40, 100, {
        "DP": [(0.9, 0.1)] * 3, "BDP": [(0.8, 0.1)] * 3, "PAC-DP": [(0.92, 0.1), (0.9, 0.1), (0.9, 0.1)],
    })  # fmt: skip
    pusht = _study(tmp_path / "pusht", "pusht", 20, 100, {"DP": [(0.1, 0.2)]})  # no other method yet: no row

    table = overview.render_overview(overview.overview_rows([lift, pusht, can_longer, can])).splitlines()

    assert table[2:] == [
        # diffs +0.2, 0, +0.1 (mean +0.1): wins; std of 0.5 / 0.6 / 0.7 is 0.1 (ddof=1)
        "| Can, 20 | 100 | 0.600 ± 0.100 | 0.400 ± 0.000 | **0.700 ± 0.100** | **+0.100** (2 / 1 / 0): wins "
        "| 0.300 → 0.100 | 0.781 / 0.865 / 0.906 |",
        # one seed: no spread, no verdict; the paper's values stand on the first Can 20 row only
        "| Can, 20 | 200 | 0.500 (seed 0 only) | **0.520** (seed 0 only) | 0.480 (seed 0 only) "
        "| -0.020 (0 / 0 / 1): seed 0 of 3 | 0.300 → 0.100 | |",
        # +0.02 in one seed of three: a mean of +0.007, under one rollout in 50, is a tie
        "| Lift, 40 | 100 | 0.900 ± 0.000 | 0.800 ± 0.000 | **0.907 ± 0.012** | +0.007 (1 / 2 / 0): ties "
        "| 0.100 → 0.100 | 0.991 / 0.994 / 0.997 |",
    ]


def test_a_budget_in_two_studies_is_refused_and_a_missing_summary_exits_2_with_one_line(tmp_path):
    cells = {"DP": [(0.5, 0.2)], "BDP": [(0.5, 0.2)], "PAC-DP": [(0.5, 0.1)]}
    first = _study(tmp_path / "first", "can", 20, 100, cells)
    second = _study(tmp_path / "second", "can", 20, 100, cells)
    for argv, message in [([first, second], "('can', 20, 100) is in both"), ([tmp_path / "nope"], "no summary.json")]:
        run = subprocess.run([sys.executable, "-m", "lerobot_pacdp.study.overview", *map(str, argv)],
                             capture_output=True, text=True, check=False)  # fmt: skip
        assert run.returncode == 2 and run.stdout == ""
        assert run.stderr.startswith(message) and len(run.stderr.strip().splitlines()) == 1


def test_the_readmes_at_a_glance_table_is_the_one_the_committed_studies_give():
    studies = sorted((REPO_ROOT / "results").glob("study_cpu_v2*"))
    table = overview.render_overview(overview.overview_rows(studies))
    assert table in (REPO_ROOT / "README.md").read_text(), (
        "README's at-a-glance table is out of date: paste `python -m lerobot_pacdp.study.overview "
        "results/study_cpu_v2*` into it"
    )


def test_budget_points_give_each_methods_final_success_per_budget_even_where_other_methods_are_missing(tmp_path):
    short = _study(tmp_path / "short", "can", 20, 100, {
        "DP": [(0.5, 0.2), (0.7, 0.2)], "BDP": [(0.4, 0.2), (0.4, 0.2)], "PAC-DP": [(0.6, 0.1), (0.8, 0.1)],
    })  # fmt: skip
    longer = _study(tmp_path / "longer", "can", 20, 300, {"PAC-DP": [(0.9, 0.1)]})  # one method, seed 0 only

    points = overview.budget_points([longer, short])

    assert list(points) == [("can", 20)]
    # DP over seeds 0, 1: mean 0.6, std (ddof=1) of 0.5 / 0.7 = sqrt(0.02) = 0.1414
    (dp,) = points[("can", 20)]["DP"]
    assert (dp.steps, dp.seeds) == (100, (0, 1)) and dp.mean == pytest.approx(0.6) and dp.std == pytest.approx(0.1414, abs=1e-4)
    assert [(p.steps, p.mean, p.std, p.seeds) for p in points[("can", 20)]["PAC-DP"]] == [
        (100, pytest.approx(0.7), pytest.approx(0.1414, abs=1e-4), (0, 1)), (300, 0.9, 0.0, (0,))
    ]
    assert overview.overview_rows([longer, short])[0].steps == 100  # the table keeps only budgets with every method


def test_the_budget_plot_is_written_through_the_cli(tmp_path):
    import matplotlib.image

    study = _study(tmp_path / "s", "lift", 20, 3000, {"DP": [(0.9, 0.1)], "BDP": [(0.9, 0.1)], "PAC-DP": [(0.8, 0.1)]})
    plot = tmp_path / "figures" / "budgets.png"
    run = subprocess.run([sys.executable, "-m", "lerobot_pacdp.study.overview", str(study), f"--budget_plot={plot}"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    assert run.returncode == 0 and run.stdout.startswith("| task, training demos |")
    height, width, _ = matplotlib.image.imread(plot).shape
    assert width > height > 100  # one panel, wider than tall
