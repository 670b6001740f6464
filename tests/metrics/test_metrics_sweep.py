"""`pacdp-metrics` over lerobot-train-shaped run directories: tables, plots, summary, resume, paired errors."""

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from lerobot_pacdp.bayesian_layers import exact_kl
from lerobot_pacdp.metrics import sweep
from lerobot_pacdp.metrics.checkpoints import MetricsError, load_policy
from lerobot_pacdp.metrics.comparison import paired_npe_difference
from lerobot_pacdp.metrics.data import EvaluationData
from lerobot_pacdp.metrics.nll_bound import GaussianBaseline
from lerobot_pacdp.metrics.noise_prediction import alphas_cumprod, noise_prediction_errors, policy_denoiser

from metrics_testing import REPO_ID, STEPS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def swept(tiny_runs, tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("metrics")
    runs = ",".join(str(tiny_runs[name]) for name in ("pacdp_s0", "pacdp_s1", "bdp_s0", "dp_s0"))
    data = [f"--dataset.repo_id={REPO_ID}", f"--dataset.root={tiny_dataset.root}", "--episodes=3-5"]
    argv = [f"--runs=[{runs}]", f"--output_dir={out}", *data, "--nll_steps=8", "--batch_size=32", "--last_k=2"]
    assert sweep.main(argv) == 0
    return out, argv


def test_one_row_per_run_and_checkpoint_in_csv_and_json(swept, tiny_runs):
    out, _ = swept
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["step"] for r in rows] == [str(s) for s in STEPS] * 4
    assert {r["label"] for r in rows} == {"PAC-DP", "BDP", "DP"}  # inferred from each checkpoint
    assert [r["policy_type"] for r in rows][-1] == "diffusion"
    for row in rows:
        assert float(row["npe"]) > 0 and float(row["npe_sem"]) > 0 and int(row["npe_examples"]) > 0
        assert float(row["nll_bound"]) <= float(row["nll_baseline"])
        assert row["success_rate"] == ""  # off by default
    stored = json.loads((out / "metrics.json").read_text())
    assert len(stored["rows"]) == 12 and stored["settings"]["seed"] == 0 and stored["settings"]["episodes"] == "3-5"
    assert stored["rows"][0]["checkpoint"] == str(tiny_runs["pacdp_s0"] / "checkpoints" / "000100" / "pretrained_model")


def test_kl_column_is_the_posterior_to_prior_kl_of_pacdp_checkpoints_only(swept):
    out, _ = swept
    rows = json.loads((out / "metrics.json").read_text())["rows"]
    for row in rows:
        if row["policy_type"] == "diffusion":
            assert row["kl"] is None
        else:
            expected = exact_kl(load_policy(Path(row["checkpoint"]), "cpu").policy.unet)
            assert row["kl"] == pytest.approx(expected) and row["kl"] >= 0
    assert any(row["kl"] for row in rows if row["label"] == "PAC-DP")  # trained posteriors moved off the prior


def test_plots_are_written(swept):
    out, _ = swept
    for name in ("npe.png", "nll_bound.png", "kl.png", "training_dynamics.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    assert not (out / "success_rate.png").exists()  # no data, no plot


def test_summary_is_the_mean_of_the_last_k_checkpoints_then_mean_std_over_runs(swept):
    out, _ = swept
    rows = json.loads((out / "metrics.json").read_text())["rows"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["last_k"] == 2
    per_run = [
        sum(r["npe"] for r in rows if r["run"].endswith(run) and r["step"] in STEPS[-2:]) / 2
        for run in ("pacdp_s0", "pacdp_s1")
    ]
    entry = summary["methods"]["PAC-DP"]
    assert entry["runs"] == 2
    assert entry["npe"]["mean"] == pytest.approx(sum(per_run) / 2)
    assert entry["npe"]["std"] == pytest.approx(abs(per_run[0] - per_run[1]) / math.sqrt(2))  # sample std
    assert summary["methods"]["DP"]["npe"]["std"] == 0.0
    assert entry["nll_bound_bits"]["mean"] == pytest.approx(entry["nll_bound"]["mean"] / math.log(2))


def test_resume_reuses_stored_rows_and_labels_group_runs(swept, tiny_runs, monkeypatch, capsys):
    out, argv = swept
    monkeypatch.setattr(sweep, "load_policy", lambda *a, **k: pytest.fail("a stored checkpoint was re-evaluated"))
    runs = f"{tiny_runs['pacdp_s0']},{tiny_runs['bdp_s0']}"
    assert sweep.main([f"--runs=[{runs}]", "--labels=[mine,mine]", *argv[1:]]) == 0
    summary = json.loads((out / "summary.json").read_text())["methods"]
    assert list(summary) == ["mine"] and summary["mine"]["runs"] == 2
    assert "mine (2 runs)" in capsys.readouterr().out


def test_a_single_checkpoint_is_a_run_of_one_on_the_same_draws(swept, tiny_runs, tmp_path):
    out, argv = swept
    step_dir = tiny_runs["pacdp_s0"] / "checkpoints" / f"{STEPS[-1]:06d}"
    assert sweep.list_checkpoints(step_dir) == [(STEPS[-1], step_dir / "pretrained_model")]
    single = tmp_path / "single"
    assert sweep.main([f"--runs=[{step_dir / 'pretrained_model'}]", f"--output_dir={single}", *argv[2:]]) == 0
    [row] = json.loads((single / "metrics.json").read_text())["rows"]
    [full] = [r for r in json.loads((out / "metrics.json").read_text())["rows"] if r["checkpoint"] == row["checkpoint"]]
    assert row["step"] == STEPS[-1] and row["npe"] == full["npe"] and row["nll_bound"] == full["nll_bound"]


def test_nll_baseline_is_fitted_to_the_complete_held_out_chunks(tiny_runs, tiny_dataset):
    loaded = load_policy(tiny_runs["pacdp_s1"] / "checkpoints" / "000200")
    data = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [3, 4, 5])
    result = sweep.evaluate_checkpoint(loaded, data, nll_steps=sweep.evenly_spaced_steps(100, 5))
    chunks = []
    for index in data.positions:  # by hand: normalise each window, keep those without padding
        frame = loaded.preprocessor(
            {k: v.unsqueeze(0) if torch.is_tensor(v) else v for k, v in data.dataset[index].items()}
        )
        if not frame["action_is_pad"].any():
            chunks.append(frame["action"].flatten())
    baseline = GaussianBaseline.fit(torch.stack(chunks))
    assert result.nll.num_examples == len(chunks) and result.nll.dim == 8 * 2
    assert result.nll.baseline_nats_per_dim == pytest.approx(baseline.entropy / baseline.dim, rel=1e-9)
    assert len(result.nll.log_snr) == 5 and result.nll.log_snr[0] == pytest.approx(7.37, abs=0.01)


def test_a_rollout_pass_repeats_exactly_because_the_policys_noise_is_seeded(tiny_runs):
    """The envs are seeded by LeRobot's loop; the diffusion noise and a pacdp weight sample come from the global
    generators, which `rollout_outcome` seeds too (and then restores, so the caller's stream is untouched)."""
    from lerobot.envs.configs import PushtEnv

    loaded = load_policy(sweep.list_checkpoints(tiny_runs["pacdp_s1"])[-1][1])
    loaded.policy.config.inference_mode = "sample"
    env_cfg = PushtEnv(obs_type="environment_state_agent_pos", episode_length=3)
    select_action = loaded.policy.select_action
    actions: list[torch.Tensor] = []
    loaded.policy.select_action = lambda batch: actions.append(select_action(batch)) or actions[-1]

    def one_pass(seed: int) -> list[torch.Tensor]:
        actions.clear()
        sweep.rollout_outcome(loaded, env_cfg, n_envs=1, n_episodes=2, seed=seed)
        return list(actions)

    torch.manual_seed(123)
    first = one_pass(seed=0)
    after_rollouts = torch.rand(1)
    torch.manual_seed(123)
    assert torch.equal(after_rollouts, torch.rand(1))  # the caller's stream goes on as if no rollout drew from it
    again, other_seed = one_pass(seed=0), one_pass(seed=1)
    assert len(first) == len(again) == 6  # 2 episodes x 3 steps
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(first, other_seed, strict=True))


def test_success_rate_through_lerobots_eval_loop(tiny_runs, tmp_path, monkeypatch):
    """The tiny policies are PushT-shaped (agent xy + 16 keypoints -> xy), so gym-pusht can roll them out.

    Held-out episodes come from the run's own split (train_config.json) here. LeRobot's loop closes the
    envs it is given (a closed robomimic env cannot reset), so every checkpoint gets its own."""
    import lerobot.envs.factory

    made = []
    make_env = lerobot.envs.factory.make_env
    monkeypatch.setattr(lerobot.envs.factory, "make_env", lambda *a, **k: made.append(1) or make_env(*a, **k))
    argv = [
        f"--runs=[{tiny_runs['pacdp_s1']}]",
        f"--output_dir={tmp_path}",
        "--nll=false",
        "--env.type=pusht",
        "--env.obs_type=environment_state_agent_pos",
        "--env.episode_length=3",
        "--eval_episodes=1",
        "--eval_batch_size=1",
    ]
    assert sweep.main(argv) == 0
    rows = json.loads((tmp_path / "metrics.json").read_text())["rows"]
    assert len(rows) == len(STEPS) == len(made)
    assert all(r["success_rate"] == 0.0 and r["nll_bound"] is None for r in rows)  # 3 steps cannot push the T home
    assert (tmp_path / "success_rate.png").read_bytes()[:8] == PNG_MAGIC
    assert not (tmp_path / "nll_bound.png").exists()


def test_rows_carry_bits_clustered_errors_and_the_step0_error(swept):
    out, _ = swept
    rows = json.loads((out / "metrics.json").read_text())["rows"]
    with open(out / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert header == sweep.CSV_COLUMNS  # the study's columns first, unchanged; the new ones after them
    for row in rows:
        assert row["nll_bound_bits"] == pytest.approx(row["nll_bound"] / math.log(2))
        assert row["nll_baseline_bits"] == pytest.approx(row["nll_baseline"] / math.log(2))
        assert row["nll_paper_compatible_bits"] is None  # --nll_steps=8: not every step was evaluated
        assert row["npe_clusters"] == 3 and row["npe_sem"] > 0 and row["npe_sem_iid"] > 0
        counts, sums = row["npe_episode_counts"], row["npe_episode_sums"]
        assert row["npe_episodes"] == [3, 4, 5] and sum(counts) == row["npe_examples"]
        assert row["npe"] == pytest.approx(sum(sums) / sum(counts))
        assert row["nll_steps"][0] == 0 and len(row["heldout_error_per_step"]) == len(row["nll_steps"]) == 8
        assert row["heldout_error_step0"] == row["heldout_error_per_step"][0] > 0


def test_paired_npe_difference_of_two_checkpoints_equals_the_per_window_computation(swept, tiny_runs, tiny_dataset):
    out, _ = swept
    rows = {r["checkpoint"]: r for r in json.loads((out / "metrics.json").read_text())["rows"]}
    paths = [tiny_runs[name] / "checkpoints" / "000300" / "pretrained_model" for name in ("pacdp_s0", "bdp_s0")]
    difference = paired_npe_difference(rows[str(paths[0])], rows[str(paths[1])])
    errors = []
    for path in paths:  # by hand: each checkpoint's per-window errors on the same seeded draws
        loaded = load_policy(path)
        data = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [3, 4, 5])
        batch = next(data.batches(loaded, batch_size=len(data)))
        denoiser = policy_denoiser(loaded.policy, batch.global_cond)
        alpha_bar = alphas_cumprod(loaded.policy)
        errors.append(noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed=0))
    gap, episode = errors[0] - errors[1], batch.episode
    assert difference.mean == pytest.approx(gap.mean().item(), rel=1e-5)  # float32 batches of 32 vs one
    residuals = torch.stack([(gap[episode == e] - gap.mean()).sum() for e in (3, 4, 5)])
    assert difference.sem == pytest.approx(math.sqrt(3 / 2 * residuals.square().sum().item()) / len(gap), rel=1e-4)
    with pytest.raises(MetricsError, match="per-episode NPE sums"):
        paired_npe_difference({"checkpoint": "old"}, rows[str(paths[1])])


def test_with_every_diffusion_step_the_row_has_the_paper_compatible_value(tiny_runs, tiny_dataset, tmp_path):
    checkpoint = tiny_runs["pacdp_s1"] / "checkpoints" / "000300"
    argv = [f"--runs=[{checkpoint}]", f"--output_dir={tmp_path}", f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={tiny_dataset.root}", "--episodes=3-5"]  # fmt: skip
    assert sweep.main(argv) == 0
    [row] = json.loads((tmp_path / "metrics.json").read_text())["rows"]
    assert len(row["nll_steps"]) == 100 and math.isfinite(row["nll_paper_compatible_bits"])
    assert (tmp_path / "nll_paper_compatible_bits.png").read_bytes()[:8] == PNG_MAGIC
