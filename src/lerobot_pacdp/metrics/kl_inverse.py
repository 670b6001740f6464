"""Inverse of the binary KL divergence, the function every PAC-Bayes-kl certificate is stated in.

kl^-1(q, c) = sup{p in [q, 1] : kl(q || p) <= c} (Seeger 2002; Perez-Ortiz et al. 2021, Eq. 4).
"""

import math


def binary_kl(q: float, p: float) -> float:
    """kl(q || p) between Bernoulli(q) and Bernoulli(p), with 0 log 0 = 0 (inf where p excludes q's mass)."""
    if not (0.0 <= q <= 1.0 and 0.0 <= p <= 1.0):
        raise ValueError(f"binary_kl needs q and p in [0, 1], got q={q}, p={p}")

    def term(a: float, b: float) -> float:
        if a == 0.0:
            return 0.0
        return math.inf if b == 0.0 else a * math.log(a / b)

    return term(q, p) + term(1.0 - q, 1.0 - p)


def kl_inverse(q: float, c: float, tol: float = 1e-12, max_iter: int = 200) -> float:
    """The largest p in [q, 1] with kl(q || p) <= c, by bisection in float64.

    kl(q || .) increases on [q, 1], so bisection keeps kl(q || lo) <= c < kl(q || hi) and the *upper*
    end of the final bracket is returned: the bound stays valid (>= the exact inverse) at any tol.
    """
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"kl_inverse needs an empirical risk q in [0, 1], got {q}")
    if not c >= 0.0:
        raise ValueError(f"kl_inverse needs a complexity c >= 0, got {c}")
    if c == 0.0 or q == 1.0:
        return q
    if binary_kl(q, 1.0) <= c:
        return 1.0
    lo, hi = q, 1.0
    for _ in range(max_iter):
        if hi - lo <= tol:
            break
        mid = 0.5 * (lo + hi)
        if binary_kl(q, mid) > c:
            hi = mid
        else:
            lo = mid
    return hi
