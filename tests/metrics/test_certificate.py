"""The PAC-Bayes certificate: its arithmetic by hand, and on a tiny PAC-DP checkpoint end to end."""

import json
import math

import pytest
import torch
import torch.nn.functional as F  # noqa: N812
from safetensors.torch import load_file

from lerobot_pacdp.bayesian_layers import sampled_weights
from lerobot_pacdp.metrics.certificate import (
    certification_windows,
    certify,
    clipped_losses,
    held_out_certificate,
    main,
    monte_carlo_risks,
    pac_bayes_certificate,
    per_demo_means,
    trivial_losses,
)
from lerobot_pacdp.metrics.checkpoints import load_policy
from lerobot_pacdp.metrics.data import EvaluationData
from lerobot_pacdp.metrics.kl_inverse import binary_kl
from lerobot_pacdp.metrics.noise_prediction import (
    WEIGHT_STREAM,
    WINDOW_STREAM,
    alphas_cumprod,
    example_generator,
    noise_prediction_errors,
    policy_denoiser,
)

from metrics_testing import REPO_ID


def test_two_stage_certificate_by_hand():
    risks, kl, n, delta, delta_prime = [0.1, 0.2, 0.3] * 100, 5.0, 500, 0.025, 0.01
    cert = pac_bayes_certificate(risks, kl, n, delta, delta_prime, trivial_risk=0.9)
    assert cert.empirical_risk == pytest.approx(0.2)
    # Stage 1: kl(R_m || stage1) = ln(2/delta') / m, stage1 > R_m.
    assert cert.stage1 > 0.2
    assert binary_kl(0.2, cert.stage1) == pytest.approx(math.log(2 / delta_prime) / 300, rel=1e-6)
    # Stage 2: kl(stage1 || stage2) = (KL + ln(2 sqrt(N) / delta)) / N with N = 500 demonstrations.
    complexity = (kl + math.log(2 * math.sqrt(n) / delta)) / n
    assert binary_kl(cert.stage1, cert.stage2) == pytest.approx(complexity, rel=1e-6)
    # Paper Eq. 5 at the stage-1 risk; the kl form is tighter than its Pinsker relaxation.
    b = kl + math.log(2 * math.sqrt(n) / delta)
    assert cert.relaxed_eq5 == pytest.approx(cert.stage1 + math.sqrt(2 * cert.stage1 * b / n) + 2 * b / n)
    assert cert.stage2 < cert.relaxed_eq5
    assert not cert.vacuous and cert.confidence == pytest.approx(1 - delta - delta_prime)
    # Stage 2 at R_m itself: what the certificate would be without stage 1's Monte Carlo slack.
    assert binary_kl(0.2, cert.stage2_at_empirical_risk) == pytest.approx(complexity, rel=1e-6)
    assert 0 < cert.stage1_share == pytest.approx(cert.stage2 - cert.stage2_at_empirical_risk)


def test_stage1_slack_shrinks_with_the_number_of_weight_samples():
    """kl^-1(0.05, ln(2/0.01)/m): m = 100 inflates a risk of 0.05 to ~0.15 (issue 10), m = 10^4 to ~0.06."""
    small = pac_bayes_certificate([0.05] * 100, kl=0.0, num_demos=100, delta=0.025, delta_prime=0.01)
    large = pac_bayes_certificate([0.05] * 10_000, kl=0.0, num_demos=100, delta=0.025, delta_prime=0.01)
    assert 0.12 < small.stage1 < 0.16 and 0.055 < large.stage1 < 0.06
    assert large.stage1_share < small.stage1_share / 5


def test_a_huge_kl_is_flagged_vacuous():
    cert = pac_bayes_certificate([0.05] * 10, kl=1e6, num_demos=100, delta=0.025, delta_prime=0.01, trivial_risk=0.9)
    assert cert.stage2 == 1.0 and cert.vacuous
    # Below 1 but above what predicting eps_hat = 0 achieves is vacuous too.
    cert = pac_bayes_certificate([0.5], kl=0.0, num_demos=10**6, delta=0.025, delta_prime=0.01, trivial_risk=0.6)
    assert cert.stage2 < 1.0 and cert.vacuous


def test_held_out_bound_by_hand():
    cert = held_out_certificate([0.1, 0.3, 0.2, 0.2], delta=0.05, trivial_risk=0.9)
    assert cert.risk == pytest.approx(0.2) and cert.num_demos == 4
    assert binary_kl(0.2, cert.bound) == pytest.approx(math.log(1 / 0.05) / 4, rel=1e-6)
    assert not cert.vacuous


def test_per_demo_means_average_within_episodes():
    losses = torch.tensor([[1.0], [3.0], [10.0], [0.0], [2.0]])
    episodes = torch.tensor([7, 7, 2, 9, 9])
    torch.testing.assert_close(
        per_demo_means(losses, episodes), torch.tensor([[10.0], [2.0], [1.0]], dtype=torch.float64)
    )


def _kl_from_safetensors(path) -> float:
    """KL(Q||P) by hand from the saved mu, rho, prior mean and prior rho (no model code) of the acting
    (EMA) network, saved under the usual `diffusion.` keys."""
    tensors = {k: v.double() for k, v in load_file(path).items()}
    total = 0.0
    for key in tensors:
        if key.startswith("diffusion.") and key.endswith("_rho") and not key.endswith("prior_rho"):
            name = key[: -len("_rho")]
            layer = name.rsplit(".", 1)[0]
            sq, sp = F.softplus(tensors[key]), F.softplus(tensors[f"{layer}.prior_rho"])
            gap = tensors[name] - tensors[f"{name}_prior_mu"]
            total += (0.5 * (torch.log(sp**2 / sq**2) + (sq**2 + gap**2) / sp**2 - 1)).sum().item()
    return total


@pytest.fixture(scope="module")
def pacdp_checkpoint(tiny_runs, tiny_dataset):
    loaded = load_policy(tiny_runs["frozen_s0"] / "checkpoints" / "000300")
    train = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [0, 1])
    test = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [3, 4, 5])
    return loaded, train, test


def test_certificate_of_a_tiny_checkpoint_matches_a_manual_computation(pacdp_checkpoint):
    loaded, train, test = pacdp_checkpoint
    clip, m = 1.5, 3
    report = certify(loaded, train, test, clip=clip, num_weight_samples=m, seed=4, batch_size=7, progress=False)
    pb = report.pac_bayes
    assert pb.num_demos == 2 and pb.num_weight_samples == m and pb.delta == loaded.policy.config.delta
    assert pb.kl == pytest.approx(_kl_from_safetensors(loaded.path / "model.safetensors"), rel=1e-12)
    assert pb.kl > 0
    assert "data-free reference" in report.fixed_tensors

    # Manually, one window at a time: clip each window's MSE at C and divide by C. The posterior mean is
    # averaged over every window of a demo, then over demos. Weight sample j (the network drawn from
    # generator (seed, j)) is scored on one window: a uniform demo, then a uniform window of it, both drawn
    # from generator (seed, j, window).
    policy, alpha_bar = loaded.policy, alphas_cumprod(loaded.policy)
    windows = {e: [] for e in train.episodes}
    for batch in train.batches(loaded, batch_size=1):
        windows[batch.episode.item()].append(batch)

    def loss(batch) -> float:
        denoiser = policy_denoiser(policy, batch.global_cond)
        error = noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed=4)
        return min(error.item(), clip) / clip

    mean_network = sum(sum(map(loss, w)) / len(w) for w in windows.values()) / 2
    sample_risks = []
    for j in range(m):
        u = torch.rand(2, generator=example_generator(4, j, WINDOW_STREAM), dtype=torch.float64)
        demo = list(windows.values())[int(u[0] * 2)]
        with sampled_weights(policy.unet, example_generator(4, j, WEIGHT_STREAM)):
            sample_risks.append(loss(demo[int(u[1] * len(demo))]))
    assert report.train_risk_mean_network == pytest.approx(mean_network, rel=1e-6)
    assert pb.empirical_risk == pytest.approx(sum(sample_risks) / m, rel=1e-6)
    assert len(set(sample_risks)) == m  # the m networks (and windows) differ
    expected = pac_bayes_certificate(sample_risks, pb.kl, 2, pb.delta, 0.01, pb.trivial_risk)
    assert pb.stage1 == pytest.approx(expected.stage1, rel=1e-6)
    assert pb.stage2 == pytest.approx(expected.stage2, rel=1e-6)
    # A random tiny net with a data-free prior and N = 2 certifies nothing, and says so.
    assert pb.vacuous and "VACUOUS" in report.summary()
    assert report.held_out is not None and report.held_out.num_demos == 3


def test_stage1_draws_demos_uniformly_then_any_of_their_windows(pacdp_checkpoint):
    loaded, train, _ = pacdp_checkpoint
    windows = certification_windows(loaded, train, seed=0)
    drawn = torch.tensor([windows.random_window(example_generator(0, j, WINDOW_STREAM)) for j in range(600)])
    per_demo = torch.bincount(windows.episode.cpu()[drawn])
    assert (windows.episode == 0).sum() != (windows.episode == 1).sum()  # 11 and 15 windows...
    assert abs(per_demo[0].item() / 600 - 0.5) < 0.06  # ...yet each demo is drawn half the time
    assert set(drawn.tolist()) == set(range(len(windows)))  # and every window of it can be


def test_clipping_at_a_tiny_c_saturates_every_loss(pacdp_checkpoint):
    loaded, train, _ = pacdp_checkpoint
    windows = certification_windows(loaded, train, seed=0)
    assert torch.all(clipped_losses(loaded.policy, windows, clip=1e-9) == 1.0)
    assert torch.all(trivial_losses(windows, clip=1e-9) == 1.0)
    assert torch.all(monte_carlo_risks(loaded.policy, windows, 1e-9, num_samples=2, seed=0, progress=False) == 1.0)


def test_cli_writes_the_report(tiny_runs, tmp_path, capsys):
    out = tmp_path / "cert.json"
    rc = main(
        [f"--checkpoint={tiny_runs['frozen_s0'] / 'checkpoints' / 'last'}", "--num_weight_samples=2", f"--output={out}"]
    )
    assert rc == 0
    report = json.loads(out.read_text())
    assert report["train_episodes"] == [0, 1, 2] and report["heldout_episodes"] == [3, 4, 5]  # the run's split
    assert report["pac_bayes"]["num_demos"] == 3 and report["pac_bayes"]["num_weight_samples"] == 2
    printed = capsys.readouterr().out
    assert "stage 2" in printed and "stage 1's share of the certificate" in printed


def _refused(argv, capsys, *phrases) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.splitlines()[-1].startswith("pacdp-certify: error: "), err
    for phrase in phrases:
        assert phrase in err, err
    return err


def test_certify_refuses_a_checkpoint_whose_deterministic_tensors_were_trained(tiny_runs, tmp_path, capsys):
    out = tmp_path / "cert.json"
    argv = [f"--checkpoint={tiny_runs['pacdp_s0'] / 'checkpoints' / 'last'}", "--num_weight_samples=2", f"--output={out}"]
    _refused(argv, capsys, "not the data-free reference", "cond_encoder.1.weight (max |difference|", "of 50 tensors differ",
             "--policy.freeze_deterministic=true")  # fmt: skip
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_certify_refuses_test_episodes_the_checkpoint_trained_on(tiny_runs, tmp_path, capsys):
    out = tmp_path / "cert.json"
    checkpoint = tiny_runs["frozen_s0"] / "checkpoints" / "last"
    argv = [f"--checkpoint={checkpoint}", "--train_episodes=2", "--test_episodes=0-1,3", f"--output={out}"]
    _refused(argv, capsys, "--test_episodes includes 2 demonstrations the checkpoint was trained on ([0, 1]",
             "trains on 3 episodes, [0, 1, 2]")  # fmt: skip
    _refused([*argv[:1], "--test_episodes=2-3", f"--output={out}"], capsys, "trained on ([2]")
    _refused([*argv[:1], "--train_episodes=3-4", "--test_episodes=4-5"], capsys, "both certified and held out ([4])")
    assert not out.exists()
