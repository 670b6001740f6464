"""The Kong et al. NLL-bound estimator on data whose entropy and optimal denoiser are known in closed form."""

import math

import pytest
import torch
from diffusers import DDPMScheduler

from lerobot_pacdp.metrics.nll_bound import (
    GaussianBaseline,
    NllAccumulator,
    log_snr,
    nll_bound_from_gain,
    nll_step_errors,
    paper_compatible_nll,
)

CHUNK = (2, 2)  # (horizon, action_dim): d = 4
D = 4
WIDE = torch.sigmoid(torch.linspace(-20.0, 20.0, 201, dtype=torch.float64))  # log-SNR grid covering all the gain


def cosine_schedule() -> torch.Tensor:
    """The policy's training schedule (100 squaredcos_cap_v2 DDPM steps)."""
    return DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2").alphas_cumprod.double()


def bound(denoiser, chunks: torch.Tensor, alpha_bar: torch.Tensor, seed: int = 0, batch: int = 500):
    """Run the estimator exactly as the sweep does: batches of (errors, chunks, frame indices)."""
    steps = range(len(alpha_bar))
    accumulator = NllAccumulator(alpha_bar, steps, seed)
    for start in range(0, len(chunks), batch):
        x = chunks[start : start + batch]
        index = torch.arange(start, start + len(x))
        accumulator.add(nll_step_errors(denoiser, x, index, alpha_bar, steps, seed), x, index)
    return accumulator.result()


class Mixture:
    """Equal-weight mixture of N(mu_k, s^2 I): exact log-density and exact eps-posterior mean."""

    def __init__(self, means: torch.Tensor, s: float):
        self.means, self.s = means.double(), s

    def sample(self, n: int, seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        component = torch.randint(len(self.means), (n,), generator=generator)
        return self.means[component] + self.s * torch.randn(n, D, generator=generator, dtype=torch.float64)

    def entropy_per_dim(self, n: int = 200_000) -> float:
        x = self.sample(n, seed=123)
        log_components = -0.5 * ((x[:, None] - self.means) ** 2).sum(-1) / self.s**2 - 0.5 * D * math.log(
            2 * math.pi * self.s**2
        )
        return -(torch.logsumexp(log_components, 1) - math.log(len(self.means))).mean().item() / D

    def denoiser(self, alpha_bar: torch.Tensor):
        def denoise(noisy, steps):
            ab = alpha_bar[steps].unsqueeze(-1)
            z = noisy.double().flatten(1)
            var = ab * self.s**2 + 1 - ab  # z | k ~ N(sqrt(ab) mu_k, var I)
            diff = z[:, None] - ab.sqrt()[:, None] * self.means
            weights = torch.softmax(-0.5 * (diff**2).sum(-1) / var, dim=1)
            eps_given_k = ((1 - ab).sqrt() / var)[:, None] * diff
            return (weights[..., None] * eps_given_k).sum(1).reshape(noisy.shape)

        return denoise


@pytest.fixture(scope="module")
def mixture() -> Mixture:
    return Mixture(torch.tensor([[1.0, -0.5, 0.3, 0.8], [-1.0, 0.5, -0.2, -0.6], [0.2, 1.0, -1.0, 0.1]]), s=0.1)


def test_gaussian_data_with_its_exact_optimal_denoiser_gives_the_true_entropy():
    generator = torch.Generator().manual_seed(0)
    basis, _ = torch.linalg.qr(torch.randn(D, D, generator=generator, dtype=torch.float64))
    eigenvalues = torch.tensor([2.0, 0.5, 0.05, 0.002], dtype=torch.float64)
    mean = torch.tensor([0.3, -0.2, 0.1, 0.0], dtype=torch.float64)
    truth = GaussianBaseline(mean, eigenvalues, basis)  # N(mean, basis diag(l) basis^T)
    chunks = (
        mean + (torch.randn(4000, D, generator=generator, dtype=torch.float64) * eigenvalues.sqrt()) @ basis.T
    ).reshape(-1, *CHUNK)
    true_entropy = truth.entropy / D
    result = bound(truth.denoiser(cosine_schedule()), chunks, cosine_schedule())
    assert result.nats_per_dim == pytest.approx(true_entropy, abs=0.01)
    assert result.baseline_nats_per_dim == pytest.approx(true_entropy, abs=0.01)


def test_mixture_bound_matches_the_true_entropy_and_is_far_below_the_gaussian_baseline(mixture):
    chunks = mixture.sample(2000, seed=1).reshape(-1, *CHUNK)
    true_entropy = mixture.entropy_per_dim()  # -0.61 nats/dim (h_G / d = +0.18)
    wide = bound(mixture.denoiser(WIDE), chunks, WIDE)
    assert wide.nats_per_dim == pytest.approx(true_entropy, abs=0.02)
    assert wide.baseline_nats_per_dim > true_entropy + 0.4  # the test is informative: the gain is large
    # On the policy's log-SNR range [-15.2, 7.4] part of the gain is cut off: still a bound, still close.
    schedule = bound(mixture.denoiser(cosine_schedule()), chunks, cosine_schedule())
    assert true_entropy - 0.02 <= schedule.nats_per_dim <= true_entropy + 0.05


def test_a_denoiser_no_better_than_the_baseline_gets_exactly_h_g_per_dim(mixture):
    chunks = mixture.sample(600, seed=2).reshape(-1, *CHUNK)
    baseline = GaussianBaseline.fit(chunks.flatten(1))
    alpha_bar = cosine_schedule()
    for denoiser in (baseline.denoiser(alpha_bar), lambda noisy, steps: torch.zeros_like(noisy)):
        result = bound(denoiser, chunks, alpha_bar)
        assert result.nats_per_dim == result.baseline_nats_per_dim == baseline.entropy / D


def test_baseline_entropy_and_mmse_closed_forms():
    eigenvalues = torch.tensor([4.0, 0.25], dtype=torch.float64)
    baseline = GaussianBaseline(torch.zeros(2, dtype=torch.float64), eigenvalues, torch.eye(2, dtype=torch.float64))
    assert baseline.entropy == pytest.approx(math.log(2 * math.pi * math.e) + 0.5 * math.log(4.0 * 0.25))
    a = torch.tensor([0.0], dtype=torch.float64)
    assert baseline.mmse(a).item() == pytest.approx(4.0 / 5.0 + 0.25 / 1.25)  # sigmoid(log l) = l / (1 + l)
    # Its denoiser is the exact posterior mean, so its error integrates to the I-MMSE identity:
    # 1/2 * integral of [d sigmoid(a) - mmse_G(a)] da = 1/2 sum log l_i (here 0).
    grid = torch.linspace(-40, 40, 4001, dtype=torch.float64)
    assert torch.trapezoid(2 * torch.sigmoid(grid) - baseline.mmse(grid), grid).item() == pytest.approx(0.0, abs=1e-6)


def test_the_policy_schedule_spans_the_documented_log_snr_range():
    a = log_snr(cosine_schedule())
    assert a[0].item() == pytest.approx(7.37, abs=0.01)
    assert a[-1].item() == pytest.approx(-15.23, abs=0.01)
    assert torch.all(a[1:] < a[:-1])


def test_per_step_draws_do_not_depend_on_the_batch_or_on_which_steps_are_evaluated(mixture):
    chunks = mixture.sample(6, seed=3).reshape(-1, *CHUNK)
    alpha_bar = cosine_schedule()
    denoiser = mixture.denoiser(alpha_bar)
    index = torch.arange(100, 106)
    full = nll_step_errors(denoiser, chunks, index, alpha_bar, range(100), seed=7)
    split = torch.cat(
        [
            nll_step_errors(denoiser, chunks[:2], index[:2], alpha_bar, range(100), 7),
            nll_step_errors(denoiser, chunks[2:], index[2:], alpha_bar, range(100), 7),
        ]
    )
    subset = nll_step_errors(denoiser, chunks, index, alpha_bar, [3, 50, 99], seed=7)
    torch.testing.assert_close(full, split, rtol=0, atol=0)
    torch.testing.assert_close(full[:, [3, 50, 99]], subset, rtol=0, atol=0)
    assert not torch.equal(full, nll_step_errors(denoiser, chunks, index, alpha_bar, range(100), seed=8))


def test_at_pusht_shape_the_bound_holds_and_the_paper_compatible_value_is_biased_far_below_the_truth():
    """d = 32 (horizon 16 x 2 actions), covariance eigenvalues from 1 down to 1e-5, exact denoiser.

    The bound equals the true entropy (the Gaussian baseline is the truth, so no gain is claimed) and
    never goes below it. The paper-compatible estimate (not a bound) snaps the 39 of its 100 log-SNRs that
    lie above the schedule's top (7.37) to step 0 and compares step 0's error with the Gaussian's error at
    the requested log-SNR: it comes out 1.68 nats/dim (2.4 bits/dim) *below* the true entropy, and below
    the floor that any bound on the schedule's log-SNR range can reach (a denoiser with zero error).
    """
    d, generator = 32, torch.Generator().manual_seed(0)
    basis, _ = torch.linalg.qr(torch.randn(d, d, generator=generator, dtype=torch.float64))
    truth = GaussianBaseline(torch.zeros(d, dtype=torch.float64), torch.logspace(0, -5, d, dtype=torch.float64), basis)
    chunks = ((torch.randn(2000, d, generator=generator, dtype=torch.float64) * truth.eigenvalues.sqrt()) @ basis.T)
    alpha_bar = cosine_schedule()
    result = bound(truth.denoiser(alpha_bar), chunks.reshape(-1, 16, 2), alpha_bar)
    true_entropy = truth.entropy / d  # -1.459 nats/dim
    assert true_entropy - 0.002 <= result.nats_per_dim <= true_entropy + 0.002
    assert result.bits_per_dim == pytest.approx(result.nats_per_dim / math.log(2))
    paper = result.paper_compatible
    assert paper is not None and paper.fraction_above_schedule == pytest.approx(0.39)
    assert all(k == 0 for a, k in zip(paper.log_snr, paper.steps, strict=True) if a > 7.37)
    assert paper.nats_per_dim == pytest.approx(true_entropy - 1.68, abs=0.02)
    assert paper.bits_per_dim == pytest.approx(paper.nats_per_dim / math.log(2))
    a = log_snr(alpha_bar)
    floor = nll_bound_from_gain(a, truth.mmse(a), truth)  # the bound of a perfect (zero-error) denoiser
    assert paper.nats_per_dim < floor < true_entropy


def test_the_paper_compatible_value_needs_every_step_and_is_the_logistic_estimate_by_hand():
    eigenvalues = torch.tensor([1.0, 0.1], dtype=torch.float64)
    baseline = GaussianBaseline(torch.zeros(2, dtype=torch.float64), eigenvalues, torch.eye(2, dtype=torch.float64))
    alpha_bar = cosine_schedule()
    zero_error = torch.zeros(100, dtype=torch.float64)
    result = paper_compatible_nll(alpha_bar, zero_error, baseline)
    # By hand: loc = -mean(log l) = 1.151, scale = sqrt(1 + 3/pi * var(log l)) with the unbiased variance.
    loc, scale = -math.log(0.1) / 2, math.sqrt(1 + 3 / math.pi * (math.log(0.1) ** 2 / 2))
    u = torch.rand(100, generator=torch.Generator().manual_seed(0)).double()
    p = torch.sigmoid(torch.tensor(-4.0)).item() + (torch.sigmoid(torch.tensor(4.0)).item() - torch.sigmoid(torch.tensor(-4.0)).item()) * u
    a = torch.sort(loc + scale * torch.log(p / (1 - p))).values
    w = scale * math.tanh(2.0) / (torch.sigmoid((a - loc) / scale) * torch.sigmoid(-(a - loc) / scale))
    expected = (baseline.entropy - 0.5 * (w * baseline.mmse(a)).mean().item()) / 2  # zero error: gap = mmse_G
    assert result.nats_per_dim == pytest.approx(expected, rel=1e-9)
    torch.testing.assert_close(torch.tensor(result.log_snr, dtype=torch.float64), a)
    with pytest.raises(ValueError, match="every step"):
        paper_compatible_nll(alpha_bar, zero_error[:50], baseline)
