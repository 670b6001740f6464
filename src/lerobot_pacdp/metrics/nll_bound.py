"""Variational NLL bound of Kong et al. (ICLR 2023, "Information-Theoretic Diffusion"), per dimension, and
the paper-compatible estimator (not a bound) that the PAC-DP paper's numbers most likely come from.

With log-SNR a = log(alpha_bar / (1 - alpha_bar)) (so alpha_bar = sigmoid(a)) and Kong et al.'s pointwise
I-MMSE relation with a Gaussian reference (written in eps-prediction form and log-SNR measure, as their
released `test_nll` evaluates it),

    -log p(x | o) = h_G - 1/2 * integral over a of [mmse_G(a) - mmse(x, a | o)] da,

where h_G = d/2 log(2 pi e) + 1/2 sum_i log l_i is the entropy of the Gaussian with the data's mean and
covariance (eigenvalues l_i), mmse_G(a) = sum_i sigmoid(a + log l_i) is that Gaussian's optimal
eps-prediction error, and mmse(x, a | o) = E||eps - eps_hat(z_a, a, o)||^2 summed over the d = horizon x
action_dim dimensions of the action chunk. Any denoiser's error is >= the optimal one, and the optimal
one is <= mmse_G (the Gaussian is the worst case for a given covariance, and conditioning on the
observation window o can only help), so

    NLL <= h_G - 1/2 * integral over [a_min, a_max] of clamp(mmse_G(a) - m(a), 0) da,

with m(a_k) the denoiser's error averaged over the evaluation set at each diffusion step k, integrated
with the trapezoid rule over the schedule's log-SNRs (the integral outside the schedule's range is
bounded by zero gain). A denoiser no better than the Gaussian baseline gets exactly h_G / d.

The estimator pairs the denoiser's error with the Gaussian baseline's own optimal (linear) denoiser on
the *same* draws, gain_k = mean_i (||eps - eps_hat_G||^2 - ||eps - eps_hat||^2): its expectation over eps
is exactly mmse_G(a_k) - m(a_k), but the chi-square noise of ||eps||^2 cancels. Without the pairing, at
log-SNRs where the model is no better than the baseline, clamping the noisy difference at 0 biases the
bound low by O(1/sqrt(n)) (measured: -0.03 nats/dim with 4000 examples of a 4-d Gaussian mixture, where
the paired estimator is within 0.01 of the true entropy); paired, a denoiser equal to the baseline gets
exactly h_G / d.

Choices:
- The Gaussian baseline is matched to the mean and covariance (1/n) of the *evaluated* (held-out)
  normalised action chunks: the identity above holds for the evaluation distribution only with its own
  moments (with training moments, mmse_G could fall below the held-out linear MMSE and the clamp would no
  longer be conservative). Eigenvalues are floored at `EIGENVALUE_FLOOR`, which only raises the bound.
- Only windows whose whole action chunk is real (no copy-padding at an episode edge) enter, so every
  example has the same dimension d.
- Conditional on the observation window: the denoiser sees o, the baseline does not.
- No bound on the discretisation: the trapezoid over the schedule's ~100 log-SNRs is an approximation.
- Reported in nats per dimension and in bits per dimension (nats / ln 2), the unit the paper's tables use.

Paper-compatible estimator (NOT a bound; `paper_compatible_nll`). A public adaptation of Kong et al.'s
code to Diffusion Policy (class `DiffusionModel_IT` in the public repository mohammadYg/diffusion_policy;
not the paper's own code) estimates -log p with Kong's importance-sampled logistic log-SNR range and a
DDPM-trained denoiser: 100 log-SNRs a_j from a logistic distribution with loc = -mean(log l_i), scale =
sqrt(1 + 3/pi var(log l_i)), truncated at +-4 scales (quantiles from seed 0), importance weights w_j,
each a_j snapped to the DDPM step k_j whose alpha_bar is nearest sigmoid(a_j), and
    NLL = h_G - 1/2 mean_j w_j clamp(mmse_G(a_j) - m(k_j), 0)   (covariance with 1/(n-1)),
printed in bits per dimension. Where a_j lies above the schedule's largest log-SNR (7.37 for the cosine
schedule; on PushT-like chunks, whose covariance has eigenvalues down to 1e-5, about half the points do),
the step-0 error m(0) is compared with mmse_G(a_j) at the *requested* a_j, which grows towards d: the
gap counts information the denoiser was never tested on, so the estimate falls below the true entropy
(tested on Gaussian data with its exact denoiser). Here m(k) is the same per-step error the bound uses
(one eps per example and step), so the estimator needs every step of the schedule evaluated.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from lerobot_pacdp.metrics.checkpoints import MetricsError
from lerobot_pacdp.metrics.noise_prediction import NLL_STREAM, Denoiser, diffuse, example_generator

EIGENVALUE_FLOOR = 1e-12
_LOG_2PI_E = math.log(2 * math.pi * math.e)
NATS_PER_BIT = math.log(2.0)
# The public adaptation's integration settings (Kong et al.'s test-time defaults).
PAPER_POINTS, PAPER_CLIP, PAPER_SEED = 100, 4.0, 0


def log_snr(alpha_bar: Tensor) -> Tensor:
    """a = log(alpha_bar / (1 - alpha_bar)), the inverse of alpha_bar = sigmoid(a)."""
    alpha_bar = alpha_bar.double()
    return torch.log(alpha_bar) - torch.log1p(-alpha_bar)


@dataclass(frozen=True)
class GaussianBaseline:
    """Kong et al.'s reference: the Gaussian with the evaluated chunks' mean and covariance."""

    mean: Tensor  # (d,) float64
    eigenvalues: Tensor  # (d,) float64, floored
    eigenvectors: Tensor  # (d, d) float64, columns

    @classmethod
    def fit(cls, chunks: Tensor, ddof: int = 0) -> "GaussianBaseline":
        """Moments of (n, d) flattened chunks; the 1/n covariance (ddof 0), so that the baseline denoiser's
        mean error over these very chunks has expectation exactly `mmse` (see the module docstring)."""
        chunks = chunks.double()
        mean = chunks.mean(0)
        centred = chunks - mean
        eigenvalues, eigenvectors = torch.linalg.eigh(centred.T @ centred / (chunks.shape[0] - ddof))
        return cls(mean, eigenvalues.clamp_min(EIGENVALUE_FLOOR), eigenvectors)

    @property
    def dim(self) -> int:
        return self.eigenvalues.numel()

    @property
    def entropy(self) -> float:
        """h_G = d/2 log(2 pi e) + 1/2 sum log l_i, in nats."""
        return 0.5 * self.dim * _LOG_2PI_E + 0.5 * self.eigenvalues.log().sum().item()

    def mmse(self, log_snr: Tensor) -> Tensor:
        """mmse_G(a) = sum_i sigmoid(a + log l_i): the optimal (linear) eps-prediction error at log-SNR a."""
        return torch.sigmoid(log_snr.double().unsqueeze(-1) + self.eigenvalues.log()).sum(-1)

    def denoiser(self, alpha_bar: Tensor) -> Denoiser:
        """The Gaussian's exact eps-posterior mean: sqrt(1-ab) (ab S + (1-ab) I)^-1 (z - sqrt(ab) mu)."""
        alpha_bar = alpha_bar.double()

        def denoise(noisy: Tensor, steps: Tensor) -> Tensor:
            ab = alpha_bar.to(noisy.device)[steps].unsqueeze(-1)
            basis = self.eigenvectors.to(noisy.device)
            coords = (noisy.double().flatten(1) - ab.sqrt() * self.mean.to(noisy.device)) @ basis
            coords = coords * (1 - ab).sqrt() / (ab * self.eigenvalues.to(noisy.device) + 1 - ab)
            return (coords @ basis.T).reshape(noisy.shape).to(noisy.dtype)

        return denoise


def nll_bound_from_gain(log_snrs: Tensor, gain: Tensor, baseline: GaussianBaseline) -> float:
    """h_G/d - 1/(2d) * trapezoid over sorted a_k of clamp(gain_k, 0), in nats per dimension.

    gain_k estimates mmse_G(a_k) - m(a_k); the clamp keeps the bound conservative (the true gain of the
    optimal denoiser is >= 0) and the log-SNRs outside the schedule contribute nothing.
    """
    order = torch.argsort(log_snrs.double())
    a = log_snrs.double()[order]
    integral = torch.trapezoid(gain.double()[order].clamp_min(0.0), a).item() if a.numel() > 1 else 0.0
    return (baseline.entropy - 0.5 * integral) / baseline.dim


@torch.no_grad()
def nll_step_errors(
    denoiser: Denoiser, actions: Tensor, indices: Tensor, alpha_bar: Tensor, steps: Sequence[int], seed: int
) -> Tensor:
    """||eps - eps_hat(z_k, k)||^2 summed over the chunk, for each example and each diffusion step k in `steps`.

    Returns (B, len(steps)) float64. Each example draws one eps per step of the *whole* schedule from its
    own generator, so the draw at step k does not depend on which steps are evaluated, on the batch, or
    on the denoiser (the baseline's errors are computed on the very same draws).
    """
    chunk_shape = tuple(actions.shape[1:])
    noise = torch.stack(
        [
            torch.randn((len(alpha_bar), *chunk_shape), generator=example_generator(seed, i, NLL_STREAM))
            for i in indices.tolist()
        ]
    ).to(actions.device, actions.dtype)
    alpha_bar = alpha_bar.to(actions.device, actions.dtype)
    errors = []
    for k in steps:
        step = torch.full((actions.shape[0],), k, dtype=torch.long, device=actions.device)
        eps = noise[:, k]
        noisy = diffuse(actions, eps, alpha_bar[step])
        errors.append((denoiser(noisy, step) - eps).double().square().sum(dim=(1, 2)))
    return torch.stack(errors, dim=1)


@dataclass(frozen=True)
class PaperCompatibleNll:
    """The public adaptation's estimate (module docstring): NOT a bound, for comparison with the paper."""

    nats_per_dim: float
    log_snr: list[float]  # the requested a_j, sorted
    steps: list[int]  # the DDPM step each a_j was snapped to
    weights: list[float]  # importance weights w_j
    fraction_above_schedule: float  # share of the a_j beyond the schedule's largest log-SNR

    @property
    def bits_per_dim(self) -> float:
        return self.nats_per_dim / NATS_PER_BIT


def paper_compatible_nll(alpha_bar: Tensor, step_mmse: Tensor, baseline: GaussianBaseline) -> PaperCompatibleNll:
    """Kong et al.'s logistic-integrated estimate with each log-SNR snapped to the nearest DDPM step.

    `step_mmse[k]` is the denoiser's mean summed squared error at step k, for every step of the schedule;
    `baseline` the Gaussian fitted with the unbiased (1/(n-1)) covariance, as the adaptation fits it.
    """
    alpha_bar = alpha_bar.double()
    if step_mmse.numel() != alpha_bar.numel():
        raise ValueError("the paper-compatible estimate needs the error at every step of the schedule")
    log_eigs = baseline.eigenvalues.log()
    loc, scale = -log_eigs.mean().item(), math.sqrt(1.0 + 3.0 / math.pi * log_eigs.var().item())
    u = torch.rand(PAPER_POINTS, generator=torch.Generator().manual_seed(PAPER_SEED)).double()
    low, high = torch.sigmoid(torch.tensor(-PAPER_CLIP)).item(), torch.sigmoid(torch.tensor(PAPER_CLIP)).item()
    a = torch.sort(loc + scale * torch.logit(low + (high - low) * u)).values
    weights = scale * math.tanh(PAPER_CLIP / 2) / (torch.sigmoid((a - loc) / scale) * torch.sigmoid(-(a - loc) / scale))
    steps = torch.argmin((torch.sigmoid(a).unsqueeze(1) - alpha_bar.unsqueeze(0)).abs(), dim=1)
    gap = (baseline.mmse(a) - step_mmse.double()[steps]).clamp_min(0.0)
    nats = (baseline.entropy - 0.5 * (weights * gap).mean().item()) / baseline.dim
    return PaperCompatibleNll(
        nats_per_dim=nats,
        log_snr=a.tolist(),
        steps=steps.tolist(),
        weights=weights.tolist(),
        fraction_above_schedule=(a > log_snr(alpha_bar).max()).double().mean().item(),
    )


@dataclass(frozen=True)
class NllBound:
    nats_per_dim: float  # the bound on -log p(action chunk | observation window) / d
    baseline_nats_per_dim: float  # h_G / d: what a denoiser no better than the Gaussian gets
    dim: int
    num_examples: int
    steps: list[int]  # the evaluated diffusion steps k
    log_snr: list[float]  # a_k of the evaluated steps
    mmse: list[float]  # m(a_k): the denoiser's mean error (summed over the d dimensions)
    mmse_gaussian: list[float]  # mmse_G(a_k)
    gain: list[float]  # paired estimate of mmse_G(a_k) - m(a_k), before the clamp
    paper_compatible: PaperCompatibleNll | None  # only when every step of the schedule was evaluated

    @property
    def bits_per_dim(self) -> float:
        return self.nats_per_dim / NATS_PER_BIT

    @property
    def baseline_bits_per_dim(self) -> float:
        return self.baseline_nats_per_dim / NATS_PER_BIT

    @property
    def error_per_step(self) -> list[float]:
        """m(a_k) / d: the held-out denoising error per dimension at each evaluated step (the NPE's scale)."""
        return [m / self.dim for m in self.mmse]


class NllAccumulator:
    """Collects the denoiser's per-step errors over the evaluation set; `result` adds the baseline's.

    The complete chunks are kept (n x d floats) so the baseline is fitted to exactly the evaluated set
    and its errors are recomputed afterwards on the same per-example draws.
    """

    def __init__(self, alpha_bar: Tensor, steps: Sequence[int], seed: int):
        self.alpha_bar = alpha_bar.double().cpu()
        self.steps = list(steps)
        self.seed = seed
        self.chunks: list[Tensor] = []
        self.indices: list[Tensor] = []
        self.errors: list[Tensor] = []

    def add(self, step_errors: Tensor, actions: Tensor, indices: Tensor) -> None:
        """Add the (B, K) errors of B complete (unpadded) chunks `actions` (B, T, D) with frame `indices`."""
        self.errors.append(step_errors.detach().cpu())
        self.chunks.append(actions.detach().to("cpu", torch.float64))
        self.indices.append(indices.cpu())

    def result(self, batch_size: int = 1024) -> NllBound:
        count = sum(len(i) for i in self.indices)
        dim = self.chunks[0][0].numel() if self.chunks else 0
        if count <= dim:
            raise MetricsError(
                f"the NLL bound fits a {dim}-d covariance and needs more complete (unpadded) action chunks than "
                f"that, got {count}; evaluate on more or longer episodes (or pass --nll=false)."
            )
        chunks, indices, errors = torch.cat(self.chunks), torch.cat(self.indices), torch.cat(self.errors)
        baseline = GaussianBaseline.fit(chunks.flatten(1))
        denoise = baseline.denoiser(self.alpha_bar)
        baseline_errors = torch.cat(
            [
                nll_step_errors(
                    denoise,
                    chunks[i : i + batch_size],
                    indices[i : i + batch_size],
                    self.alpha_bar,
                    self.steps,
                    self.seed,
                )
                for i in range(0, count, batch_size)
            ]
        )
        log_snrs = log_snr(self.alpha_bar)[self.steps]
        gain = (baseline_errors - errors).mean(0)
        paper = None
        if sorted(self.steps) == list(range(len(self.alpha_bar))):
            step_mmse = torch.empty(len(self.steps), dtype=torch.float64)
            step_mmse[self.steps] = errors.mean(0)
            paper = paper_compatible_nll(self.alpha_bar, step_mmse, GaussianBaseline.fit(chunks.flatten(1), ddof=1))
        return NllBound(
            nats_per_dim=nll_bound_from_gain(log_snrs, gain, baseline),
            baseline_nats_per_dim=baseline.entropy / baseline.dim,
            dim=baseline.dim,
            num_examples=count,
            steps=list(self.steps),
            log_snr=log_snrs.tolist(),
            mmse=errors.mean(0).tolist(),
            mmse_gaussian=baseline.mmse(log_snrs).tolist(),
            gain=gain.tolist(),
            paper_compatible=paper,
        )
