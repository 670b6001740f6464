"""The PAC-Bayes certificate: its arithmetic by hand, and on a tiny PAC-DP checkpoint end to end."""

import json
import math

import pytest
import torch
import torch.nn.functional as F  # noqa: N812
from safetensors.torch import load_file

from lerobot_pacdp.bayesian_layers import sampled_weights
from lerobot_pacdp.metrics.certificate import (
    certify,
    clipped_demo_losses,
    held_out_certificate,
    main,
    pac_bayes_certificate,
    per_demo_means,
)
from lerobot_pacdp.metrics.checkpoints import load_policy
from lerobot_pacdp.metrics.data import EvaluationData
from lerobot_pacdp.metrics.kl_inverse import binary_kl
from lerobot_pacdp.metrics.noise_prediction import (
    WEIGHT_STREAM,
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
    """KL(Q||P) by hand from the saved mu, rho, prior mean and prior rho (no model code)."""
    tensors = {k: v.double() for k, v in load_file(path).items()}
    total = 0.0
    for key in tensors:
        if key.endswith("_rho") and not key.endswith("prior_rho"):
            name = key[: -len("_rho")]
            layer = name.rsplit(".", 1)[0]
            sq, sp = F.softplus(tensors[key]), F.softplus(tensors[f"{layer}.prior_rho"])
            gap = tensors[name] - tensors[f"{name}_prior_mu"]
            total += (0.5 * (torch.log(sp**2 / sq**2) + (sq**2 + gap**2) / sp**2 - 1)).sum().item()
    return total


@pytest.fixture(scope="module")
def pacdp_checkpoint(tiny_runs, tiny_dataset):
    loaded = load_policy(tiny_runs["pacdp_s0"] / "checkpoints" / "000300")
    train = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [0, 1])
    test = EvaluationData(loaded.policy.config, REPO_ID, tiny_dataset.root, [3, 4, 5])
    return loaded, train, test


def test_certificate_of_a_tiny_checkpoint_matches_a_manual_computation(pacdp_checkpoint):
    loaded, train, test = pacdp_checkpoint
    clip, m = 1.5, 2
    report = certify(loaded, train, test, clip=clip, num_weight_samples=m, seed=4, batch_size=7, progress=False)
    pb = report.pac_bayes
    assert pb.num_demos == 2 and pb.num_weight_samples == m and pb.delta == loaded.policy.config.delta
    assert pb.kl == pytest.approx(_kl_from_safetensors(loaded.path / "model.safetensors"), rel=1e-12)
    assert pb.kl > 0

    # Manually, one window at a time: clip each example's MSE at C, divide by C, average per demo,
    # then over demos; weight sample j is the network drawn from generator (seed, j).
    policy, alpha_bar = loaded.policy, alphas_cumprod(loaded.policy)
    per_demo = {e: [[] for _ in range(m + 1)] for e in train.episodes}

    def loss(batch) -> float:
        denoiser = policy_denoiser(policy, batch.global_cond)
        error = noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed=4)
        return min(error.item(), clip) / clip

    for batch in train.batches(loaded, batch_size=1):
        for j in range(m):
            with sampled_weights(policy.unet, example_generator(4, j, WEIGHT_STREAM)):
                per_demo[batch.episode.item()][j].append(loss(batch))
        per_demo[batch.episode.item()][m].append(loss(batch))
    demo_means = torch.tensor([[sum(v) / len(v) for v in per_demo[e]] for e in train.episodes], dtype=torch.float64)
    sample_risks = demo_means[:, :m].mean(0)
    assert pb.empirical_risk == pytest.approx(sample_risks.mean().item(), rel=1e-6)
    assert report.train_risk_mean_network == pytest.approx(demo_means[:, m].mean().item(), rel=1e-6)
    assert len(set(sample_risks.tolist())) == m  # the m networks differ
    expected = pac_bayes_certificate(sample_risks.tolist(), pb.kl, 2, pb.delta, 0.01, pb.trivial_risk)
    assert pb.stage1 == pytest.approx(expected.stage1, rel=1e-6)
    assert pb.stage2 == pytest.approx(expected.stage2, rel=1e-6)
    # A random tiny net with a data-free prior and N = 2 certifies nothing, and says so.
    assert pb.vacuous and "VACUOUS" in report.summary()
    assert report.held_out is not None and report.held_out.num_demos == 3


def test_clipping_at_a_tiny_c_saturates_every_loss(pacdp_checkpoint):
    loaded, train, _ = pacdp_checkpoint
    losses = clipped_demo_losses(loaded, train, clip=1e-9, seed=0, num_weight_samples=2)
    for values in losses.values():
        assert torch.all(values == 1.0)


def test_cli_writes_the_report(tiny_runs, tmp_path, capsys):
    out = tmp_path / "cert.json"
    rc = main(
        [f"--checkpoint={tiny_runs['bdp_s0'] / 'checkpoints' / 'last'}", "--num_weight_samples=2", f"--output={out}"]
    )
    assert rc == 0
    report = json.loads(out.read_text())
    assert report["train_episodes"] == [0, 1, 2] and report["heldout_episodes"] == [3, 4, 5]  # the run's split
    assert report["pac_bayes"]["num_demos"] == 3
    assert "stage 2" in capsys.readouterr().out
