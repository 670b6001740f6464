"""The success rate with its 95% interval, and the run summary, against hand computations."""

import json
import math

import pytest

from lerobot_pacdp.rollout_summary import (
    SuccessRate,
    average_max_reward,
    main,
    success_rate_of,
    wilson_interval,
)


def test_wilson_interval_matches_the_closed_form_by_hand():
    # 45 of 50: p = 0.9, z = 1.96: centre (0.9 + 1.96^2/100) / (1 + 1.96^2/50), half-width z sqrt(p q/n + z^2/(4 n^2)) / (1 + z^2/n)
    z = 1.959963984540054
    centre = (0.9 + z * z / 100) / (1 + z * z / 50)
    half = z * math.sqrt(0.9 * 0.1 / 50 + z * z / 10000) / (1 + z * z / 50)
    low, high = wilson_interval(45, 50)
    assert (low, high) == pytest.approx((centre - half, centre + half), abs=1e-12)
    assert (low, high) == pytest.approx((0.7864, 0.9565), abs=1e-4)


def test_wilson_interval_stays_inside_zero_one_at_the_extremes():
    assert wilson_interval(50, 50)[1] == 1.0 and wilson_interval(50, 50)[0] == pytest.approx(0.9287, abs=1e-4)
    assert wilson_interval(0, 50)[0] == 0.0 and wilson_interval(0, 50)[1] == pytest.approx(0.0713, abs=1e-4)
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def _eval_info(successes: list[bool], seeds: list[int] | None = None) -> dict:
    seeds = seeds if seeds is not None else list(range(1000, 1000 + len(successes)))
    return {"per_episode": [{"episode_ix": i, "success": s, "seed": seeds[i]} for i, s in enumerate(successes)]}


def test_success_rate_counts_episodes_and_refuses_repeated_seeds():
    assert success_rate_of(_eval_info([True, False, True, True])) == SuccessRate(3, 4)
    per_task = {"per_task": [{"task_id": 0, "metrics": {"successes": [True, False]}},
                             {"task_id": 1, "metrics": {"successes": [True, True, False]}}]}  # LeRobot 0.6.1's layout
    assert success_rate_of(per_task) == SuccessRate(3, 5)
    assert str(SuccessRate(45, 50)) == "90.0% (45/50 episodes; 95% interval 78.6-95.7%)"
    with pytest.raises(ValueError, match="distinct seeds"):
        success_rate_of(_eval_info([True, True], seeds=[7, 7]))


def test_runs_split_over_processes_pool_their_episodes_and_must_not_share_seeds():
    first, second = _eval_info([True, True, False], seeds=[1000, 1001, 1002]), _eval_info([False, True], seeds=[1003, 1004])
    assert success_rate_of(first, second) == SuccessRate(3, 5)
    per_task = {"per_task": [{"task_id": 0, "metrics": {"successes": [True]}}]}
    assert success_rate_of(first, per_task) == SuccessRate(3, 4)
    with pytest.raises(ValueError, match="5 episodes do not have distinct seeds"):
        success_rate_of(first, _eval_info([False, True], seeds=[1002, 1003]))


def test_average_max_reward_pools_the_best_reward_of_every_episode_over_processes():
    # LeRobot 0.6.1's per-task layout in one process, per-episode rows in the other: (1 + 0.5 + 0.25 + 0.75) / 4
    per_task = {"per_task": [{"task_id": 0, "metrics": {"successes": [True, False], "max_rewards": [1.0, 0.5]}}]}
    per_episode = {"per_episode": [{"success": False, "seed": 3, "max_reward": 0.25},
                                   {"success": False, "seed": 4, "max_reward": 0.75}]}
    assert average_max_reward(per_task, per_episode) == pytest.approx(0.625)
    assert average_max_reward(per_task) == pytest.approx(0.75)
    # an episode without a recorded reward makes the average undefined, not biased
    assert average_max_reward(per_task, _eval_info([True])) is None
    assert average_max_reward({"per_task": [{"task_id": 0, "metrics": {"successes": [True]}}]}) is None


def test_the_cli_writes_the_summary_and_names_a_missing_input(tmp_path, capsys):
    checkpoint = tmp_path / "checkpoints" / "000040" / "pretrained_model"
    checkpoint.mkdir(parents=True)
    (checkpoint / "config.json").write_text(json.dumps({"type": "pacdp", "bayesian": True, "kl_weight": 1e-5, "prior_rho": -4.5}))
    (checkpoint.parent / "training_state").mkdir()
    (checkpoint.parent / "training_state" / "training_step.json").write_text(json.dumps({"step": 40}))
    (tmp_path / "eval_info.json").write_text(json.dumps(_eval_info([True] * 9 + [False])))
    metrics = {"rows": [{"checkpoint": str(checkpoint), "npe": 0.25, "npe_sem": 0.01}]}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    output = tmp_path / "summary.json"
    args = [f"--eval_info=[{tmp_path / 'eval_info.json'}]", f"--checkpoint={checkpoint}", "--task=lift",
            f"--metrics={tmp_path / 'metrics.json'}", "--wall_time_s=12.5", f"--output={output}"]
    assert main(args) == 0
    summary = json.loads(output.read_text())
    assert summary["success_rate"] == 0.9 and summary["n_episodes"] == 10 and summary["train_steps"] == 40
    assert summary["ci95"] == pytest.approx(list(wilson_interval(9, 10)))
    assert summary["heldout_npe"] == 0.25 and summary["wall_time_s"] == 12.5
    assert summary["avg_max_reward"] is None  # these episodes carry no rewards
    assert summary["policy"] == "pacdp PAC-DP (kl_weight=1e-05, prior_rho=-4.5)"
    assert "success rate: 90.0% (9/10 episodes" in capsys.readouterr().out

    missing = [a if not a.startswith("--eval_info") else f"--eval_info=[{tmp_path / 'nope.json'}]" for a in args]
    assert main([*missing[:-1], f"--output={tmp_path / 'other.json'}"]) == 2
    assert "nope.json does not exist" in capsys.readouterr().err
    assert not (tmp_path / "other.json").exists()
