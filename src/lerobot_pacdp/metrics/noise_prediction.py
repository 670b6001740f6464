"""Noise-prediction error (NPE, paper Sec. IV) with paired, reproducible draws.

Every example's diffusion step t and noise eps come from a generator seeded by (seed, the example's
global frame index): two checkpoints are compared on identical draws, whatever the batch size, the
device or the order of the batches, so their NPE difference is not blurred by Monte Carlo noise.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from torch import Tensor

# (noisy chunk z_t (B, T, D), diffusion step t (B,) int64) -> predicted noise eps_hat (B, T, D).
Denoiser = Callable[[Tensor, Tensor], Tensor]

# Independent random streams: per example, the NPE / certificate draw and the NLL-bound draws; per
# certificate weight sample, the network draw and the choice of one window per demonstration.
NPE_STREAM, NLL_STREAM, WEIGHT_STREAM, WINDOW_STREAM = 0, 1, 2, 3


def example_generator(seed: int, index: int, stream: int, device: str | torch.device = "cpu") -> torch.Generator:
    """A generator that depends only on (seed, index, stream): the same draws in any batch or order."""
    state = np.random.SeedSequence([seed, index, stream]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator(device=device).manual_seed(int(state))


def npe_draws(indices: Tensor, seed: int, num_steps: int, chunk_shape: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    """One diffusion step t ~ U{0..num_steps-1} and one eps ~ N(0, I) per example, seeded per index."""
    steps, noise = [], []
    for index in indices.tolist():
        generator = example_generator(seed, index, NPE_STREAM)
        steps.append(torch.randint(num_steps, (), generator=generator))
        noise.append(torch.randn(chunk_shape, generator=generator))
    return torch.stack(steps), torch.stack(noise)


def diffuse(actions: Tensor, noise: Tensor, alpha_bar: Tensor) -> Tensor:
    """Forward process, paper Eq. 1: x_t = sqrt(alpha_bar_t) x_0 + sqrt(1 - alpha_bar_t) eps."""
    alpha_bar = alpha_bar.reshape(-1, *([1] * (actions.dim() - 1)))
    return alpha_bar.sqrt() * actions + (1 - alpha_bar).sqrt() * noise


def alphas_cumprod(policy: DiffusionPolicy) -> Tensor:
    """alpha_bar_t of the policy's training noise schedule, float64 on the CPU."""
    return policy.diffusion.noise_scheduler.alphas_cumprod.detach().to("cpu", torch.float64)


def policy_denoiser(policy: DiffusionPolicy, global_cond: Tensor) -> Denoiser:
    """The policy's eps-prediction for one batch of observation windows (x_0-predicting nets converted)."""
    unet = policy.diffusion.unet
    alpha_bar = alphas_cumprod(policy).to(global_cond.device, global_cond.dtype)
    predicts_sample = policy.config.prediction_type == "sample"

    def denoise(noisy: Tensor, steps: Tensor) -> Tensor:
        output = unet(noisy, steps, global_cond=global_cond)
        if not predicts_sample:
            return output
        ab = alpha_bar[steps].reshape(-1, 1, 1)  # eps = (x_t - sqrt(ab) x_0) / sqrt(1 - ab), from Eq. 1
        return (noisy - ab.sqrt() * output) / (1 - ab).sqrt()

    return denoise


def masked_errors(prediction: Tensor, noise: Tensor, valid: Tensor) -> Tensor:
    """Per-example ||eps - eps_hat||^2 averaged over the real (unpadded) entries of the chunk, (B,) float64."""
    squared = (prediction - noise).square().double() * valid.unsqueeze(-1)
    return squared.sum(dim=(1, 2)) / (valid.sum(dim=1) * noise.shape[-1]).clamp_min(1)


@torch.no_grad()
def noise_prediction_errors(
    denoiser: Denoiser, actions: Tensor, valid: Tensor, indices: Tensor, alpha_bar: Tensor, seed: int
) -> Tensor:
    """The integrand of paper Eq. 2 at each example's own seeded (t, eps): `masked_errors`, (B,) float64.

    Padding is masked as in training; every checkpoint type is masked alike so that DP and PAC-DP
    numbers compare.
    """
    steps, noise = npe_draws(indices, seed, len(alpha_bar), tuple(actions.shape[1:]))
    steps, noise = steps.to(actions.device), noise.to(actions.device, actions.dtype)
    noisy = diffuse(actions, noise, alpha_bar.to(actions.device, actions.dtype)[steps])
    return masked_errors(denoiser(noisy, steps), noise, valid)


@dataclass(frozen=True)
class MeanWithError:
    """A mean and its standard error; `clusters` is the number of independent groups the error assumes."""

    mean: float
    sem: float
    n: int
    clusters: int

    @classmethod
    def of(cls, values: Tensor) -> "MeanWithError":
        """The standard error of independent values."""
        n = values.numel()
        sem = values.double().std().item() / math.sqrt(n) if n > 1 else math.nan
        return cls(values.double().mean().item(), sem, n, n)


@dataclass(frozen=True)
class EpisodeSums:
    """Per-episode sums of per-window values: enough for a mean, its episode-clustered error and paired
    differences between checkpoints evaluated on the same windows and draws.

    The overlapping windows of one episode are correlated, so the error treats episodes, not windows, as
    the independent units (the cluster-robust variance, with the G / (G - 1) small-sample factor):
        var(mean) = G / (G - 1) * sum_g (S_g - n_g * mean)^2 / n^2.
    """

    episodes: tuple[int, ...]
    sums: tuple[float, ...]
    counts: tuple[int, ...]

    @classmethod
    def of(cls, values: Tensor, episodes: Tensor) -> "EpisodeSums":
        unique, inverse = torch.unique(episodes, return_inverse=True)
        sums = torch.zeros(len(unique), dtype=torch.float64).index_add_(0, inverse, values.double())
        counts = torch.bincount(inverse, minlength=len(unique))
        return cls(tuple(unique.tolist()), tuple(sums.tolist()), tuple(counts.tolist()))

    def mean_with_error(self) -> MeanWithError:
        sums, counts = torch.tensor(self.sums, dtype=torch.float64), torch.tensor(self.counts, dtype=torch.float64)
        n, groups = int(counts.sum().item()), len(self.sums)
        mean = sums.sum().item() / n
        if groups < 2:
            return MeanWithError(mean, math.nan, n, groups)
        residuals = sums - counts * mean
        sem = math.sqrt(groups / (groups - 1) * residuals.square().sum().item()) / n
        return MeanWithError(mean, sem, n, groups)

    def minus(self, other: "EpisodeSums") -> "EpisodeSums":
        """Per-episode sums of the paired differences (this - other) on the same windows."""
        if self.episodes != other.episodes or self.counts != other.counts:
            raise ValueError(
                "paired differences need both checkpoints evaluated on the same windows: their episodes or "
                "window counts differ (evaluate them in one pacdp-metrics run, with the same --episodes)."
            )
        return EpisodeSums(self.episodes, tuple(a - b for a, b in zip(self.sums, other.sums, strict=True)), self.counts)
