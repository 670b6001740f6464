"""The PAC-DP training objective, paper Eq. 9.

L = R + sqrt(2 R B / N) + 2 B / N,  with  B = lambda * KL(Q||P) + ln(2 sqrt(N) / delta),

where R is the empirical denoising risk of a weight sample (Eq. 10), N the number of training
samples and delta the confidence. With lambda = 1 this is the relaxed PAC-Bayes-kl bound of Eq. 5;
with lambda < 1 it is the regularised surrogate the paper trains on; lambda = 0 is BDP.
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor

# d sqrt(x)/dx is infinite at 0: keep the square root's argument away from it.
_SQRT_FLOOR = 1e-12


@dataclass(frozen=True)
class PacBayesObjective:
    """Eq. 9 and its parts, as tensors in the risk's dtype (so they backpropagate)."""

    total: Tensor
    complexity: Tensor  # B = lambda * KL + ln(2 sqrt(N) / delta)
    sqrt_term: Tensor  # sqrt(2 R B / N)
    linear_term: Tensor  # 2 B / N


def confidence_term(num_samples: int, delta: float) -> float:
    """ln(2 sqrt(N) / delta), the data-size part of the complexity in Eqs. 5 and 9."""
    return math.log(2.0 * math.sqrt(num_samples) / delta)


def pac_bayes_objective(
    risk: Tensor, kl: Tensor, num_samples: int, delta: float, kl_weight: float
) -> PacBayesObjective:
    """Evaluate Eq. 9 for an empirical risk `risk` and a divergence `kl` (any float dtype)."""
    complexity = (kl_weight * kl + confidence_term(num_samples, delta)).to(risk.dtype)
    sqrt_term = torch.sqrt(torch.clamp(2.0 * risk * complexity / num_samples, min=_SQRT_FLOOR))
    linear_term = 2.0 * complexity / num_samples
    return PacBayesObjective(
        total=risk + sqrt_term + linear_term,
        complexity=complexity,
        sqrt_term=sqrt_term,
        linear_term=linear_term,
    )
