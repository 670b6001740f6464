"""`pacdp-uncertainty` through its CLI: the analysis of recorded episodes, its errors, rollouts and the OOD check."""

import json

import numpy as np
import pytest
from test_uncertainty_eval import save_lift_checkpoint

from lerobot_pacdp.uncertainty_cli import main
from lerobot_pacdp.uncertainty_episodes import (
    UNCERTAINTY_FILE,
    EpisodeUncertainty,
    UncertaintyRecording,
    write_recording,
)


def _episode(ix: int, success: bool, posterior: float | None, noise: float) -> EpisodeUncertainty:
    length = 40 if success else 400
    steps = tuple(range(0, length, 8))
    return EpisodeUncertainty(
        "robomimic", 0, ix, 100 + ix, success, length, steps,
        None if posterior is None else (posterior,) * len(steps), (noise,) * len(steps),
    )  # fmt: skip


def _record(path, episodes, policy="pacdp PAC-DP (kl_weight=1e-05, prior_rho=-4.5)"):
    return write_recording(path / UNCERTAINTY_FILE, UncertaintyRecording(8, 8, policy, "ckpt", tuple(episodes)))


def test_the_analysis_of_recorded_episodes_writes_the_summary_and_plots(tmp_path, capsys):
    # posterior: failures 0.3, successes 0.1 (separated); noise: every failure but one above every success
    outcomes = [True] * 6 + [False] * 6
    noises = [0.2, 0.21, 0.22, 0.23, 0.24, 0.5, 0.6, 0.61, 0.62, 0.63, 0.64, 0.1]
    episodes = [_episode(i, s, 0.1 if s else 0.3, n) for i, (s, n) in enumerate(zip(outcomes, noises, strict=True))]
    first, second = _record(tmp_path / "a", episodes[::2]), _record(tmp_path / "b", episodes[1::2])
    twin = _record(tmp_path / "twin", [_episode(i, s, None, 0.4 if s else 0.2) for i, s in enumerate(outcomes)], "pacdp bayesian=false (DP twin)")
    out = tmp_path / "out"

    assert main([f"--episodes=[{first},{second.parent}]", f"--twin_episodes=[{twin}]", f"--output_dir={out}", "--splits=5", "--alpha=0.25", "--task=lift"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["task"], summary["checkpoint"], summary["n_episodes"], summary["n_failures"]) == ("lift", "ckpt", 12, 6)
    assert summary["horizon"] == 40 and summary["success_length_median"] == 40
    assert summary["auroc"] == 1.0 and summary["baseline_auroc"] == pytest.approx(30 / 36) and summary["dp_twin_auroc"] == 0.0
    # 3 of the 6 successes calibrate: the threshold is their 3rd smallest score (rank ceil(4 * 0.75)), 0.1
    assert summary["conformal_alpha"] == 0.25 and summary["detection_rate"] == 1.0 and summary["false_alarm_rate"] == 0.0
    assert summary["median_detection_lead_steps"] == 400  # the alarm comes at the first decision, step 0
    assert sorted(summary["seeds"]) == list(range(100, 112))
    assert sorted(p.name for p in out.iterdir()) == ["roc.png", "summary.json", "uncertainty_over_time.png"]
    assert "PAC-DP posterior spread: AUROC 1.000" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "pass --checkpoint=DIR with --env.type=... to roll out, or --episodes=[...]"),
        (["--episodes=[{tmp}/absent]"], "does not exist; record episodes with `lerobot-eval"),
        (["--episodes=[{tmp}/a,{tmp}/a]"], "repeat episode seeds; pool only distinct rollouts"),
        (["--episodes=[{tmp}/a]"], "AUROC needs both classes, got 0 positives and 2 negatives. Roll out more episodes"),
        (["--episodes=[{tmp}/a]", "--ood_shifts=[0.1]"], "--ood_shifts moves robomimic objects"),
        (["--episodes=[{tmp}/a]", "--samples=1"], "--samples must be at least 2"),
        (["--checkpoint={tmp}/a"], "--checkpoint needs the environment to roll out in"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, args, message):
    _record(tmp_path / "a", [_episode(0, True, 0.1, 0.2), _episode(1, True, 0.1, 0.2)])
    out = tmp_path / "out"
    assert main([a.format(tmp=tmp_path) for a in args] + [f"--output_dir={out}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-uncertainty: error: ") and message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_rollouts_are_recorded_and_kept_when_their_analysis_cannot_run(tmp_path, capsys):
    """An untrained policy fails every 6-step episode: no AUROC, but the rollouts stay for a later analysis."""
    checkpoint = save_lift_checkpoint(tmp_path / "checkpoint")
    out = tmp_path / "out"
    args = [f"--checkpoint={checkpoint}", "--env.type=robomimic", "--env.task=lift", "--env.episode_length=6",
            "--n_episodes=3", "--batch_size=2", "--samples=2", "--seed=7", f"--output_dir={out}"]  # fmt: skip
    assert main(args) == 2
    assert "AUROC needs both classes, got 3 positives and 0 negatives" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["rollouts"]
    recording = json.loads((out / "rollouts" / UNCERTAINTY_FILE).read_text())
    assert [(e["seed"], e["success"], e["length"]) for e in recording["episodes"]] == [(7, False, 6), (8, False, 6), (9, False, 6)]
    assert recording["checkpoint"] == str(checkpoint) and recording["samples"] == 2
    assert json.loads((out / "rollouts" / "eval_info.json").read_text())["overall"]["n_episodes"] == 3


@pytest.mark.slow
def test_the_ood_check_moves_the_object_by_the_shift_and_scores_every_start(tmp_path):
    from lerobot_pacdp.metrics.checkpoints import load_policy
    from lerobot_pacdp.robomimic.env import RobomimicEnv
    from lerobot_pacdp.uncertainty_ood import compare_to_unshifted, initial_observations, shifted_starts

    env = RobomimicEnv("lift", render_mode=None)
    try:
        unmoved, moved = initial_observations(env, [3, 4], 0.0), initial_observations(env, [3, 4], 0.1)
    finally:
        env.close()
    cube_xy = slice(0, 2)  # Lift's environment_state starts with cube_pos
    distance = np.linalg.norm(moved["environment_state"][:, cube_xy] - unmoved["environment_state"][:, cube_xy], axis=1)
    assert distance == pytest.approx([0.1, 0.1], abs=1e-9)
    assert np.array_equal(moved["agent_pos"], unmoved["agent_pos"])
    assert np.array_equal(moved["environment_state"][:, 2:7], unmoved["environment_state"][:, 2:7])  # height, quaternion

    loaded = load_policy(save_lift_checkpoint(tmp_path / "checkpoint"))
    results = shifted_starts(loaded.policy, loaded.preprocessor, "lift", "1.5", [3, 4, 5], [0.1], num_samples=2, batch_size=2)
    assert [(r.shift, r.n_states, len(r.posterior), len(r.noise)) for r in results] == [(0.0, 3, 3, 3), (0.1, 3, 3, 3)]
    comparisons = compare_to_unshifted(results)
    assert comparisons[0].posterior_auroc == 0.5 and comparisons[0].noise_auroc == 0.5  # a set against itself
    assert comparisons[1].posterior_mean == pytest.approx(np.mean(results[1].posterior))
