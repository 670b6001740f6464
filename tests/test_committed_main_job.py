"""The committed main-job summaries hold what issue 11 asks of them, and the README quotes them."""

import json
from pathlib import Path

import pytest

from lerobot_pacdp.rollout_summary import wilson_interval

ROOT = Path(__file__).resolve().parents[1]
SUMMARIES = {"lift": ROOT / "results/main_job/summary.json", "pusht": ROOT / "results/main_job/pusht_summary.json"}
REQUIRED = {"task", "policy", "success_rate", "n_episodes", "ci95", "heldout_npe", "train_steps", "wall_time_s"}


@pytest.mark.parametrize("task", sorted(SUMMARIES))
def test_a_committed_main_job_summary_is_consistent_with_its_own_rollouts(task):
    summary = json.loads(SUMMARIES[task].read_text())
    assert summary.keys() >= REQUIRED
    assert summary["task"] == task and summary["n_episodes"] >= 50
    assert summary["success_rate"] == pytest.approx(summary["successes"] / summary["n_episodes"])
    assert summary["ci95"] == pytest.approx(list(wilson_interval(summary["successes"], summary["n_episodes"])))


@pytest.mark.parametrize("task", sorted(SUMMARIES))
def test_the_readme_quotes_each_committed_main_job_result(task):
    summary = json.loads(SUMMARIES[task].read_text())
    readme = " ".join((ROOT / "README.md").read_text().split())
    low, high = summary["ci95"]
    assert f"{summary['successes']} of {summary['n_episodes']}" in readme
    assert f"{low:.2f}-{high:.2f}" in readme
    assert f"held-out NPE {summary['heldout_npe']:.3f}" in readme
    assert summary["wall_time_s"] > 0 and f"{int(summary['wall_time_s']) // 60} min" in readme
