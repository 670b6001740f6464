"""PAC-Bayes risk certificate of a trained PAC-DP policy (Perez-Ortiz et al. 2021's two-stage recipe).

Loss. For demonstration n, l(w, n) = mean over its windows of min(MSE_i(w), C) / C in [0, 1], where
MSE_i is the example's denoising error (paper Eq. 2 integrand, padding masked) at its own fixed draw of
(t, eps) (seeded by frame index, as the NPE). Clipping each example, not a batch mean, keeps the loss
bounded; demonstrations, not overlapping windows, are the independent units, so N = #demonstrations.

Stage 1 (Monte Carlo, m whole-network samples w_j ~ Q; Langford & Caruana 2002):
    R_S(Q) <= kl^-1(R_m, ln(2/delta') / m),   R_m = 1/m sum_j 1/N sum_n l(w_j, n).
Stage 2 (PAC-Bayes-kl, Seeger 2002 / Maurer 2004; paper Eq. 5 is its relaxation):
    R(Q) <= kl^-1(stage 1, (KL(Q||P) + ln(2 sqrt(N)/delta)) / N),
with KL the exact divergence recomputed from the saved mu, rho and prior tensors. Both hold together
with probability >= 1 - delta - delta'. For comparison, Eq. 5 (refined Pinsker relaxation) is reported
at the stage-1 risk: stage1 + sqrt(2 stage1 B / N) + 2 B / N, B = KL + ln(2 sqrt(N)/delta).

Held-out bound for the deterministic posterior-mean network on n_test unseen demonstrations (test-set
bound): R(mu) <= kl^-1(R_test, ln(1/delta) / n_test), with probability >= 1 - delta.

A certificate is vacuous when it is >= 1 or >= the clipped risk of the trivial predictor eps_hat = 0 on
the same draws (about min(1, C)/C): it then says nothing a constant predictor does not.

Validity needs a prior chosen without the certified demonstrations: the data-free prior of training,
or a prior learnt on a disjoint split (see `lerobot_pacdp.metrics.learned_prior`). Reporting the best of
k certified configurations needs delta / k.
"""

import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
import torch
from torch import Tensor

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.bayesian_layers import exact_kl, sampled_weights
from lerobot_pacdp.metrics.checkpoints import LoadedPolicy, MetricsError, UnsupportedPolicyError, load_policy, run_cli
from lerobot_pacdp.metrics.data import DatasetArgs, EvalBatch, EvaluationData, resolve_split
from lerobot_pacdp.metrics.kl_inverse import kl_inverse
from lerobot_pacdp.metrics.learned_prior import check_disjoint_from_prior
from lerobot_pacdp.metrics.noise_prediction import (
    WEIGHT_STREAM,
    Denoiser,
    alphas_cumprod,
    example_generator,
    noise_prediction_errors,
    policy_denoiser,
)
from lerobot_pacdp.objective import confidence_term, pac_bayes_objective


@dataclass(frozen=True)
class PacBayesCertificate:
    num_demos: int  # N
    num_weight_samples: int  # m
    kl: float
    delta: float
    delta_prime: float
    empirical_risk: float  # R_m
    stage1: float  # bound on the empirical risk of Q on the N demonstrations
    stage2: float  # the certificate: bound on the population risk of Q
    relaxed_eq5: float  # paper Eq. 5 at the stage-1 risk
    trivial_risk: float
    vacuous: bool
    confidence: float  # 1 - delta - delta'


@dataclass(frozen=True)
class HeldOutCertificate:
    num_demos: int  # n_test
    risk: float  # R_test of the posterior-mean network
    bound: float
    delta: float
    trivial_risk: float
    vacuous: bool
    confidence: float


def is_vacuous(bound: float, trivial_risk: float) -> bool:
    return bound >= min(1.0, trivial_risk)


def pac_bayes_certificate(
    sample_risks: Sequence[float],
    kl: float,
    num_demos: int,
    delta: float,
    delta_prime: float,
    trivial_risk: float = 1.0,
) -> PacBayesCertificate:
    """The two-stage certificate from the m per-sample empirical risks 1/N sum_n l(w_j, n)."""
    m = len(sample_risks)
    if m < 1 or num_demos < 1:
        raise ValueError(f"need >= 1 weight sample and >= 1 demonstration, got m={m}, N={num_demos}")
    empirical = math.fsum(sample_risks) / m
    stage1 = kl_inverse(empirical, math.log(2.0 / delta_prime) / m)
    complexity = kl + confidence_term(num_demos, delta)
    stage2 = kl_inverse(stage1, complexity / num_demos)
    relaxed = pac_bayes_objective(
        torch.tensor(stage1, dtype=torch.float64), torch.tensor(kl, dtype=torch.float64), num_demos, delta, 1.0
    ).total.item()
    return PacBayesCertificate(
        num_demos=num_demos,
        num_weight_samples=m,
        kl=kl,
        delta=delta,
        delta_prime=delta_prime,
        empirical_risk=empirical,
        stage1=stage1,
        stage2=stage2,
        relaxed_eq5=relaxed,
        trivial_risk=trivial_risk,
        vacuous=is_vacuous(stage2, trivial_risk),
        confidence=1.0 - delta - delta_prime,
    )


def held_out_certificate(demo_risks: Sequence[float], delta: float, trivial_risk: float = 1.0) -> HeldOutCertificate:
    """Test-set bound kl^-1(R_test, ln(1/delta)/n_test) from per-demonstration losses of one fixed network."""
    n = len(demo_risks)
    if n < 1:
        raise ValueError("the held-out bound needs >= 1 held-out demonstration")
    risk = math.fsum(demo_risks) / n
    bound = kl_inverse(risk, math.log(1.0 / delta) / n)
    return HeldOutCertificate(n, risk, bound, delta, trivial_risk, is_vacuous(bound, trivial_risk), 1.0 - delta)


def per_demo_means(losses: Tensor, episodes: Tensor) -> Tensor:
    """Average (n, ...) per-window losses within each episode: (num_episodes, ...), episodes in sorted order."""
    unique, inverse = torch.unique(episodes, return_inverse=True)
    sums = torch.zeros((len(unique), *losses.shape[1:]), dtype=torch.float64).index_add_(0, inverse, losses.double())
    counts = torch.bincount(inverse, minlength=len(unique)).double()
    return sums / counts.reshape(-1, *([1] * (losses.dim() - 1)))


def _zero_denoiser(noisy: Tensor, steps: Tensor) -> Tensor:
    return torch.zeros_like(noisy)


def clipped_losses(denoiser: Denoiser, batch: EvalBatch, alpha_bar: Tensor, seed: int, clip: float) -> Tensor:
    """min(MSE_i, C) / C per example, at the example's seeded (t, eps) draw, on the CPU."""
    errors = noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed)
    return errors.clamp(max=clip).cpu() / clip


@torch.no_grad()
def clipped_demo_losses(
    loaded: LoadedPolicy,
    data: EvaluationData,
    clip: float,
    seed: int,
    num_weight_samples: int = 0,
    weight_seed: int = 0,
    batch_size: int = 256,
    desc: str | None = None,
) -> dict[str, Tensor]:
    """Per-demonstration clipped losses, one pass over `data`.

    Returns "mean" (N,) for the posterior-mean network, "trivial" (N,) for eps_hat = 0, and, for m > 0,
    "samples" (N, m) for m whole-network weight samples; sample j is drawn from a generator seeded
    (weight_seed, j) afresh for every batch, so it is the same network across the whole pass (and across
    runs on the same device).
    """
    policy = loaded.policy
    alpha_bar = alphas_cumprod(policy)
    device = next(policy.parameters()).device
    columns: dict[str, list[Tensor]] = {"mean": [], "trivial": [], "samples": []}
    episodes = []
    for batch in data.batches(loaded, batch_size, desc=desc):
        denoiser = policy_denoiser(policy, batch.global_cond)
        columns["mean"].append(clipped_losses(denoiser, batch, alpha_bar, seed, clip))
        columns["trivial"].append(clipped_losses(_zero_denoiser, batch, alpha_bar, seed, clip))
        samples = []
        for j in range(num_weight_samples):
            with sampled_weights(policy.unet, example_generator(weight_seed, j, WEIGHT_STREAM, device)):
                samples.append(clipped_losses(denoiser, batch, alpha_bar, seed, clip))
        if samples:
            columns["samples"].append(torch.stack(samples, dim=1))
        episodes.append(batch.episode)
    episode_index = torch.cat(episodes)
    return {name: per_demo_means(torch.cat(values), episode_index) for name, values in columns.items() if values}


@dataclass
class CertificateReport:
    checkpoint: str
    clip: float
    seed: int
    train_episodes: list[int]
    pac_bayes: PacBayesCertificate
    train_risk_mean_network: float
    heldout_episodes: list[int] = field(default_factory=list)
    held_out: HeldOutCertificate | None = None

    def summary(self) -> str:
        pb, clip = self.pac_bayes, f"{self.clip:g}"
        lines = [
            f"PAC-Bayes certificate for {self.checkpoint} (loss: per-demo mean of min(MSE, {clip}) / {clip})",
            f"  N = {pb.num_demos} demonstrations, m = {pb.num_weight_samples} weight samples, KL(Q||P) = {pb.kl:.6g}",
            f"  empirical risk of Q (Monte Carlo) R_m             = {pb.empirical_risk:.5f}"
            f"   (posterior mean: {self.train_risk_mean_network:.5f})",
            f"  stage 1 kl^-1(R_m, ln(2/delta')/m)                = {pb.stage1:.5f}",
            f"  stage 2 kl^-1(stage 1, (KL+ln(2 sqrt(N)/delta))/N) = {pb.stage2:.5f}"
            f"   <- certificate, w.p. >= {pb.confidence:.3f}",
            f"  paper Eq. 5 (relaxed) at the stage-1 risk         = {pb.relaxed_eq5:.5f}",
            f"  trivial predictor (eps_hat = 0) clipped risk      = {pb.trivial_risk:.5f}",
            "  VACUOUS: the certificate is no better than the trivial bound." if pb.vacuous else "  non-vacuous.",
        ]
        if self.held_out is not None:
            ho = self.held_out
            lines += [
                f"Held-out bound for the posterior-mean network on {ho.num_demos} unseen demonstrations:",
                f"  R_test = {ho.risk:.5f}, kl^-1(R_test, ln(1/delta)/n_test) = {ho.bound:.5f},"
                f" w.p. >= {ho.confidence:.3f}" + ("  (VACUOUS)" if ho.vacuous else ""),
            ]
        return "\n".join(lines)


def require_pacdp(loaded: LoadedPolicy) -> None:
    if loaded.policy_type != "pacdp":
        raise UnsupportedPolicyError(
            f"{loaded.path} is a {loaded.policy_type!r} policy: a PAC-Bayes certificate needs the posterior and "
            "prior of a 'pacdp' checkpoint. Build one from it with `pacdp-learned-prior` and fine-tune."
        )


def certify(
    loaded: LoadedPolicy,
    train_data: EvaluationData,
    heldout_data: EvaluationData | None = None,
    *,
    clip: float = 1.0,
    num_weight_samples: int = 100,
    delta: float | None = None,
    delta_prime: float = 0.01,
    seed: int = 0,
    batch_size: int = 256,
    progress: bool = True,
) -> CertificateReport:
    """Certify a PAC-DP checkpoint on its training demonstrations (and bound its mean network on held-out ones)."""
    require_pacdp(loaded)
    if not clip > 0 or num_weight_samples < 1:
        raise MetricsError(f"need clip > 0 and num_weight_samples >= 1, got {clip} and {num_weight_samples}")
    delta = loaded.policy.config.delta if delta is None else delta
    kl = exact_kl(loaded.policy.unet)
    train = clipped_demo_losses(
        loaded,
        train_data,
        clip,
        seed,
        num_weight_samples,
        seed,
        batch_size,
        desc="certificate (training demos)" if progress else None,
    )
    trivial = train["trivial"].mean().item()
    report = CertificateReport(
        checkpoint=str(loaded.path),
        clip=clip,
        seed=seed,
        train_episodes=train_data.episodes,
        pac_bayes=pac_bayes_certificate(
            train["samples"].mean(0).tolist(), kl, len(train["mean"]), delta, delta_prime, trivial
        ),
        train_risk_mean_network=train["mean"].mean().item(),
    )
    if heldout_data is not None:
        held = clipped_demo_losses(
            loaded, heldout_data, clip, seed, batch_size=batch_size, desc="held-out demos" if progress else None
        )
        report.heldout_episodes = heldout_data.episodes
        report.held_out = held_out_certificate(held["mean"].tolist(), delta, held["trivial"].mean().item())
    return report


@dataclass
class CertifyConfig:
    """`pacdp-certify`: PAC-Bayes certificate of one PAC-DP checkpoint."""

    checkpoint: Path | None = None  # .../checkpoints/<step>/pretrained_model
    dataset: DatasetArgs = field(default_factory=DatasetArgs)
    # Demonstrations Q was trained on (certified); default: the run's training split. E.g. "70-199".
    train_episodes: str | None = None
    # Unseen demonstrations for the posterior-mean bound; default: the run's eval_split ("" for none).
    test_episodes: str | None = None
    clip: float = 1.0  # C: per-example MSE clipped at C, divided by C
    num_weight_samples: int = 100  # m
    delta: float | None = None  # default: the checkpoint's config.delta
    delta_prime: float = 0.01  # confidence of the Monte Carlo stage 1
    seed: int = 0  # per-example (t, eps) draws and the m weight samples
    batch_size: int = 256
    frame_stride: int = 1  # use every k-th window (in episode order)
    num_workers: int = 0  # DataLoader workers for the one-off read of the windows
    device: str | None = None
    output: Path | None = None  # write the report as JSON here
    # A prior built by pacdp-learned-prior: refuse to certify on the demonstrations it was trained on.
    prior: Path | None = None


def _certify_main(argv: Sequence[str] | None) -> int:
    cfg = draccus.parse(config_class=CertifyConfig, args=argv)
    if cfg.checkpoint is None:
        raise MetricsError("pass --checkpoint=<.../checkpoints/<step>/pretrained_model>")
    loaded = load_policy(cfg.checkpoint, cfg.device)
    require_pacdp(loaded)
    split = resolve_split(loaded.path, cfg.dataset, cfg.train_episodes, cfg.test_episodes)
    if cfg.prior is not None:
        check_disjoint_from_prior(cfg.prior, split.train_episodes + split.heldout_episodes)
    config = loaded.policy.config

    def data(episodes: list[int]) -> EvaluationData:
        return EvaluationData(config, split.repo_id, split.root, episodes, cfg.frame_stride, cfg.num_workers)

    train = data(split.train_episodes)
    test = data(split.heldout_episodes) if split.heldout_episodes else None
    report = certify(
        loaded,
        train,
        test,
        clip=cfg.clip,
        num_weight_samples=cfg.num_weight_samples,
        delta=cfg.delta,
        delta_prime=cfg.delta_prime,
        seed=cfg.seed,
        batch_size=cfg.batch_size,
    )
    print(report.summary())
    if cfg.output is not None:
        write_text_atomic(cfg.output, json.dumps(asdict(report), indent=2))
        print(f"wrote {cfg.output}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli("pacdp-certify", _certify_main, argv)


if __name__ == "__main__":
    sys.exit(main())
