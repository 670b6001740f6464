"""Issue 14's evidence study: the cpu_v2 preset, the study recording its scripted demos, the final-checkpoint
rows and the paired PAC-DP vs DP test."""

import dataclasses
import json

import pytest

from lerobot_pacdp.rollout_summary import wilson_interval
from lerobot_pacdp.speed_benchmark import PRESETS as SPEED_PRESETS
from lerobot_pacdp.study.data import count_episodes, prepare_dataset
from lerobot_pacdp.study.evaluation import success_checkpoints
from lerobot_pacdp.study.evidence import final_rows, paired_comparisons, render_evidence, sign_flip_p_value
from lerobot_pacdp.study.plan import plan_task
from lerobot_pacdp.study.presets import ScriptedDemos, get_preset

REFERENCES = {"lift": (1e-5, -4.5)}


def test_the_cpu_v2_preset_plans_dp_bdp_and_pacdp_on_lift_can_and_pusht_with_three_seeds(tmp_path):
    preset = get_preset("cpu_v2")
    assert [(t.name, t.demos) for t in preset.tasks] == [("lift", (20, 40)), ("can", (20, 40)), ("pusht", (20,))]
    assert preset.seeds == (0, 1, 2) and preset.success_episodes == 50 and preset.last_k == 1
    assert (preset.success_last_k, preset.success_every) == (1, 1000)  # the final checkpoint, and curves
    lift = preset.task("lift")
    specs = plan_task(lift, preset, num_episodes=count_episodes(lift, tmp_path, pusht_zarr=None))
    assert len(specs) == 2 * 3 * 3  # demos x methods x seeds
    assert {(s.method, s.kl_weight, s.prior_rho) for s in specs} == {
        ("DP", None, None), ("BDP", 0.0, -4.5), ("PAC-DP", 1e-5, -4.5)
    }
    for seed in preset.seeds:
        runs = [s for s in specs if s.seed == seed]
        heldout = set(runs[0].heldout_episodes)
        assert len(heldout) == 20 and all(heldout.isdisjoint(s.train_episodes) for s in runs)
        assert {len(s.train_episodes) for s in runs} == {20, 40}
    assert lift.steps == 3000 and lift.train_config["policy"]["optimizer_lr"] == 6e-3  # lift_cpu.json's recipe
    can = preset.task("can")
    assert (can.steps, can.save_freq, can.train_config["policy"]["optimizer_lr"]) == (20_000, 2500, 3e-3)  # can_cpu.json's
    pusht = preset.task("pusht")  # pusht/pacdp_cpu.json's all-demos recipe
    assert (pusht.steps, pusht.save_freq, pusht.reference_kl_weight) == (40_000, 10_000, 1e-5)


def test_the_cpu_study_keeps_the_unet_and_lambda_its_committed_results_ran_with():
    policy = get_preset("cpu").task("pusht").train_config["policy"]
    assert tuple(policy["down_dims"]) == SPEED_PRESETS["cpu"].down_dims  # 64/128/256, not pacdp_cpu.json's U-Net
    assert policy["kl_weight"] == 1e-4 and policy["optimizer_lr"] == 1e-3


@pytest.mark.slow
def test_the_study_records_and_converts_a_scripted_task_once(tmp_path):
    lift = dataclasses.replace(get_preset("cpu_v2").task("lift"), scripted=ScriptedDemos(num_demos=2))
    assert count_episodes(lift, tmp_path, None) == 2  # planned before the demos exist
    prepare_dataset(lift, tmp_path, None)
    info = tmp_path / "data" / "lift" / "meta" / "info.json"
    assert json.loads(info.read_text())["total_episodes"] == 2
    recorded_at = info.stat().st_mtime_ns
    prepare_dataset(lift, tmp_path, None)  # already there: nothing recorded again
    assert info.stat().st_mtime_ns == recorded_at and count_episodes(lift, tmp_path, None) == 2


def test_the_sign_flip_test_counts_sign_patterns_as_extreme_as_the_observed_one():
    # |1+2+3| = 6 is reached only by all signs + or all -: 2 of 8 patterns.
    assert sign_flip_p_value([1.0, 2.0, 3.0]) == pytest.approx(2 / 8)
    # |3-1| = 2: (+,-), (-,+) give 2 and the other two give 4: all 4 patterns.
    assert sign_flip_p_value([3.0, -1.0]) == pytest.approx(1.0)
    assert sign_flip_p_value([0.5] * 5) == pytest.approx(2 / 32)


def _row(method, seed, step, sr, npe, demos=20, kl=None, rho=None):
    kl = 0.0 if method == "BDP" else (1e-5 if method == "PAC-DP" else kl)
    rho = None if method == "DP" else -4.5 if rho is None else rho
    return {"task": "lift", "demos": demos, "method": method, "seed": seed, "step": step, "run": f"{method}{seed}{kl}{rho}{demos}",
            "success_rate": sr, "npe": npe, "nll_bound_bits": 1.0, "nll_paper_compatible_bits": 0.5,
            "kl_weight": kl, "prior_rho": rho}  # fmt: skip


def test_final_rows_keep_each_runs_last_checkpoint_at_the_reference_point_with_its_interval():
    rows = [_row("DP", 0, 500, None, 0.3), _row("DP", 0, 1000, 0.9, 0.2) | {"avg_max_reward": 0.95}, _row("PAC-DP", 0, 1000, 0.5, 0.25),
            _row("PAC-DP", 0, 1000, 0.1, 0.1, rho=-4.0), _row("BDP", 0, 1000, 0.7, 0.22)]  # fmt: skip
    summary = final_rows(rows, n_episodes=50, references=REFERENCES)
    assert [(r["method"], r["step"]) for r in summary] == [("DP", 1000), ("BDP", 1000), ("PAC-DP", 1000)]
    dp = summary[0]
    assert dp["successes"] == 45 and dp["n_episodes"] == 50 and dp["heldout_npe"] == 0.2
    assert dp["ci95"] == pytest.approx(list(wilson_interval(45, 50)))
    assert dp["avg_max_reward"] == 0.95 and summary[2]["avg_max_reward"] is None  # rolled out before scores
    assert summary[2]["prior_rho"] == -4.5  # the rho -4.0 run is off the reference point


def test_paired_comparison_matches_runs_by_demos_and_seed():
    summary = final_rows([
        _row("DP", 0, 1, 0.80, 0.20), _row("PAC-DP", 0, 1, 0.90, 0.25),
        _row("DP", 1, 1, 0.60, 0.30), _row("PAC-DP", 1, 1, 0.60, 0.28),
        _row("DP", 0, 1, 0.50, 0.40, demos=40), _row("PAC-DP", 0, 1, 0.40, 0.30, demos=40),
        _row("DP", 2, 1, 0.70, 0.30),  # no PAC-DP partner: not paired
    ], n_episodes=10, references=REFERENCES)  # fmt: skip
    by_metric = {c.metric: c for c in paired_comparisons(summary)}
    success = by_metric["success_rate"]
    assert (success.pairs, success.pacdp_better, success.ties, success.dp_better) == (3, 1, 1, 1)
    assert success.mean_difference == pytest.approx(0.0)
    assert success.p_value == pytest.approx(sign_flip_p_value([0.1, 0.0, -0.1]))
    npe = by_metric["heldout_npe"]
    assert (npe.pacdp_better, npe.dp_better) == (2, 1)  # lower NPE is better
    assert npe.mean_difference == pytest.approx((0.05 - 0.02 - 0.10) / 3)
    markdown = render_evidence(summary, paired_comparisons(summary))
    assert "| lift | 20 | DP | 0.700 ± 0.100 (n=3) |" in markdown and "s0: 8/10" in markdown
    assert "| lift | 40 | PAC-DP | 0.400 (n=1) | -- | 0.3000 (n=1) |" in markdown  # one seed; no score recorded
    # the valid bound, then the paper-compatible estimate, before the per-seed counts
    assert "| 1.000 ± 0.000 (n=3) | 0.500 ± 0.000 (n=3) | s0: 8/10, s1: 6/10, s2: 7/10 |" in markdown


def test_a_study_without_dp_says_there_is_nothing_to_pair_instead_of_an_empty_table():
    summary = final_rows([_row("PAC-DP", 0, 1, 0.90, 0.25)], n_episodes=10, references=REFERENCES)
    assert paired_comparisons(summary) == []
    markdown = render_evidence(summary, [])
    assert markdown.endswith("No (demos, seed) has both a PAC-DP and a DP run: nothing to pair.\n")
    assert "| task | metric | pairs |" not in markdown


def test_success_checkpoints_are_the_last_k_and_every_kth_step_in_step_order():
    rows = [{"checkpoint": f"c{step}", "step": step} for step in (3000, 500, 1000, 1500, 2000, 2500)]
    assert success_checkpoints(rows, last_k=1) == ["c3000"]
    assert success_checkpoints(rows, last_k=1, every=1000) == ["c1000", "c2000", "c3000"]
    assert success_checkpoints(rows, last_k=2, every=1500) == ["c1500", "c2500", "c3000"]
    assert success_checkpoints(rows, last_k=0, every=2000) == ["c2000"]
