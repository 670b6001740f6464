"""PAC-Bayes risk certificate of a trained PAC-DP policy (Perez-Ortiz et al. 2021's two-stage recipe).

Loss. For demonstration n, l(w, n) = mean over its windows i of l_i(w) = min(MSE_i(w), C) / C in [0, 1],
where MSE_i is the window's denoising error (paper Eq. 2 integrand, padding masked) at its own fixed draw
of (t, eps) (seeded by frame index, as the NPE). Clipping each window, not a batch mean, keeps the loss
bounded; demonstrations, not overlapping windows, are the independent units, so N = #demonstrations.

Stage 1 (Monte Carlo over the posterior; Langford & Caruana 2002): sample j draws a whole network
w_j ~ Q, a demonstration n_j uniformly and one of its windows u_j uniformly. X_j = l_{u_j}(w_j) are i.i.d.
in [0, 1] with mean R_S(Q) = E_w 1/N sum_n l(w, n), so with probability >= 1 - delta'
    R_S(Q) <= kl^-1(R_m, ln(2/delta') / m),   R_m = 1/m sum_j X_j.
The slack depends on m alone (not on the variance of X_j), so scoring one window per weight sample loses
nothing in the bound and makes a sample cost one weight draw and one network row instead of a pass over
every window: that is what makes the default m = 10^4 affordable (costs in results/certificate/README.md).
Stage 2 (PAC-Bayes-kl, Seeger 2002 / Maurer 2004; paper Eq. 5 is its relaxation):
    R(Q) <= kl^-1(stage 1, (KL(Q||P) + ln(2 sqrt(N)/delta)) / N),
with KL the exact divergence recomputed from the saved mu, rho and prior tensors. Both hold together
with probability >= 1 - delta - delta'. The report also gives stage 2 at R_m itself, i.e. how much of
the certificate is stage 1's Monte Carlo slack, and Eq. 5 (refined Pinsker relaxation) at the stage-1
risk: stage1 + sqrt(2 stage1 B / N) + 2 B / N, B = KL + ln(2 sqrt(N)/delta).

Held-out bound for the deterministic posterior-mean network on n_test unseen demonstrations (test-set
bound): R(mu) <= kl^-1(R_test, ln(1/delta) / n_test), with probability >= 1 - delta.

A certificate is vacuous when it is >= 1 or >= the clipped risk of the trivial predictor eps_hat = 0 on
the same draws (about min(1, C)/C): it then says nothing a constant predictor does not.

Validity needs everything but the posterior fixed before the certified demonstrations are seen: the
prior (data-free, or learnt on a disjoint split, see `lerobot_pacdp.metrics.learned_prior`) and every
deterministic tensor (`lerobot_pacdp.certification`; train with `--policy.freeze_deterministic=true`).
`certify` refuses a checkpoint where either is not so. Reporting the best of k certified configurations
needs delta / k.
"""

import json
import math
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file
from torch import Tensor
from tqdm.auto import tqdm

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.bayesian_layers import exact_kl, sampled_weights
from lerobot_pacdp.certification import (
    REFERENCE_SEED,
    data_free_reference,
    describe_differences,
    deterministic_tensors,
    prior_tensors,
    tensor_differences,
)
from lerobot_pacdp.cli_errors import run_draccus_cli
from lerobot_pacdp.episodes import EpisodeSelection, selected_episodes
from lerobot_pacdp.metrics.checkpoints import (
    LoadedPolicy,
    MetricsError,
    UnsupportedPolicyError,
    load_policy,
    resolve_pretrained_dir,
)
from lerobot_pacdp.metrics.data import (
    DatasetArgs,
    EpisodeSplit,
    EvaluationData,
    resolve_split,
    split_from_train_config,
)
from lerobot_pacdp.metrics.kl_inverse import kl_inverse
from lerobot_pacdp.metrics.learned_prior import PROVENANCE_FILE, check_disjoint_from_prior
from lerobot_pacdp.metrics.noise_prediction import (
    WEIGHT_STREAM,
    WINDOW_STREAM,
    alphas_cumprod,
    diffuse,
    example_generator,
    masked_errors,
    npe_draws,
    policy_denoiser,
)
from lerobot_pacdp.objective import confidence_term, pac_bayes_objective

DEFAULT_WEIGHT_SAMPLES = 10_000
_NETWORK_PREFIX = "diffusion."
_PROCESSOR_PATTERNS = ("policy_preprocessor*.safetensors", "policy_postprocessor*.safetensors")


class CertificationError(MetricsError):
    """The checkpoint cannot be certified soundly (something other than the posterior saw the data)."""


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
    stage2_at_empirical_risk: float  # stage 2 with R_S(Q) = R_m exactly: stage2 minus this is stage 1's share
    relaxed_eq5: float  # paper Eq. 5 at the stage-1 risk
    trivial_risk: float
    vacuous: bool
    confidence: float  # 1 - delta - delta'

    @property
    def stage1_share(self) -> float:
        """How much of the certificate is the Monte Carlo slack of stage 1."""
        return self.stage2 - self.stage2_at_empirical_risk


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
    """The two-stage certificate from the m per-sample empirical risks X_j (module docstring)."""
    m = len(sample_risks)
    if m < 1 or num_demos < 1:
        raise ValueError(f"need >= 1 weight sample and >= 1 demonstration, got m={m}, N={num_demos}")
    empirical = math.fsum(sample_risks) / m
    stage1 = kl_inverse(empirical, math.log(2.0 / delta_prime) / m)
    complexity = (kl + confidence_term(num_demos, delta)) / num_demos
    stage2 = kl_inverse(stage1, complexity)
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
        stage2_at_empirical_risk=kl_inverse(empirical, complexity),
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


@dataclass(frozen=True)
class CertificationWindows:
    """Every window of some demonstrations with its fixed (t, eps) draw, sorted by demonstration."""

    noisy: Tensor  # (n, horizon, action_dim): z_t of the window's normalised chunk
    steps: Tensor  # (n,) its diffusion step t
    noise: Tensor  # (n, horizon, action_dim) its eps
    valid: Tensor  # (n, horizon) True where the action is real
    global_cond: Tensor  # (n, cond_dim)
    episode: Tensor  # (n,) non-decreasing

    def __len__(self) -> int:
        return len(self.steps)

    @property
    def num_demos(self) -> int:
        return len(torch.unique_consecutive(self.episode))

    def random_window(self, generator: torch.Generator) -> int:
        """The row of a uniformly drawn demonstration's uniformly drawn window (stage 1's X_j)."""
        _, counts = torch.unique_consecutive(self.episode.cpu(), return_counts=True)
        u = torch.rand(2, generator=generator, dtype=torch.float64).tolist()
        demo = min(int(u[0] * len(counts)), len(counts) - 1)
        return int(counts[:demo].sum()) + min(int(u[1] * counts[demo]), int(counts[demo]) - 1)


@torch.no_grad()
def certification_windows(
    loaded: LoadedPolicy, data: EvaluationData, seed: int, batch_size: int = 256, desc: str | None = None
) -> CertificationWindows:
    """Read and normalise the windows of `data` once, with the NPE's per-window draws (seeded by frame index)."""
    alpha_bar = alphas_cumprod(loaded.policy)
    columns = defaultdict(list)
    for batch in data.batches(loaded, batch_size, desc=desc):
        device, dtype = batch.actions.device, batch.actions.dtype
        steps, noise = npe_draws(batch.index, seed, len(alpha_bar), tuple(batch.actions.shape[1:]))
        steps, noise = steps.to(device), noise.to(device, dtype)
        columns["noisy"].append(diffuse(batch.actions, noise, alpha_bar.to(device, dtype)[steps]))
        columns["steps"].append(steps)
        columns["noise"].append(noise)
        columns["valid"].append(batch.valid)
        columns["global_cond"].append(batch.global_cond)
        columns["episode"].append(batch.episode.to(device))
    stacked = {name: torch.cat(values) for name, values in columns.items()}
    order = torch.argsort(stacked["episode"], stable=True)
    return CertificationWindows(**{name: values[order] for name, values in stacked.items()})


@torch.no_grad()
def clipped_losses(
    policy, windows: CertificationWindows, clip: float, rows: Tensor | None = None, batch_size: int = 256
) -> Tensor:
    """min(MSE_i, C) / C of the policy's network as it stands (mu, or a weight sample inside
    `sampled_weights`) on the windows `rows` (default all), float64 on the CPU."""
    rows = torch.arange(len(windows)) if rows is None else rows
    rows = rows.to(windows.steps.device)
    losses = []
    for chunk in rows.split(batch_size):
        prediction = policy_denoiser(policy, windows.global_cond[chunk])(windows.noisy[chunk], windows.steps[chunk])
        errors = masked_errors(prediction, windows.noise[chunk], windows.valid[chunk])
        losses.append(errors.clamp(max=clip).cpu() / clip)
    return torch.cat(losses)


def trivial_losses(windows: CertificationWindows, clip: float) -> Tensor:
    """The clipped losses of the trivial predictor eps_hat = 0 on the same draws."""
    errors = masked_errors(torch.zeros_like(windows.noise), windows.noise, windows.valid)
    return errors.clamp(max=clip).cpu() / clip


@torch.no_grad()
def monte_carlo_risks(
    policy, windows: CertificationWindows, clip: float, num_samples: int, seed: int, progress: bool = True
) -> Tensor:
    """X_j for j < m: weight sample j (generator (seed, j)) on one random window (generator (seed, j, window))."""
    device = windows.steps.device
    risks = torch.empty(num_samples, dtype=torch.float64)
    for j in tqdm(range(num_samples), desc="stage 1: weight samples", leave=False, disable=not progress):
        row = torch.tensor([windows.random_window(example_generator(seed, j, WINDOW_STREAM))])
        with sampled_weights(policy.unet, example_generator(seed, j, WEIGHT_STREAM, device)):
            risks[j] = clipped_losses(policy, windows, clip, row)[0]
    return risks


def _preview(episodes: Sequence[int], limit: int = 10) -> str:
    shown = ", ".join(map(str, list(episodes)[:limit]))
    return f"[{shown}{', ...' if len(episodes) > limit else ''}]"


def _network_tensors(model_file: Path) -> dict[str, Tensor]:
    """The acting network's tensors in a model.safetensors, keyed like `policy.diffusion.state_dict()`."""
    return {k.removeprefix(_NETWORK_PREFIX): v for k, v in load_file(model_file).items() if k.startswith(_NETWORK_PREFIX)}


def _processor_tensors(pretrained_dir: Path) -> dict[str, Tensor]:
    """The normalisation statistics saved beside a checkpoint, keyed by file and tensor."""
    return {
        f"{path.name}:{key}": value
        for pattern in _PROCESSOR_PATTERNS
        for path in sorted(pretrained_dir.glob(pattern))
        for key, value in load_file(path).items()
    }


def learned_prior_of_run(pretrained_dir: Path) -> Path | None:
    """The `pacdp-learned-prior` directory the run started from (train_config.json's policy.pretrained_path)."""
    config_file = pretrained_dir / "train_config.json"
    if not config_file.is_file():
        return None
    try:
        start = json.loads(config_file.read_text()).get("policy", {}).get("pretrained_path")
    except (OSError, json.JSONDecodeError) as exc:
        raise MetricsError(f"cannot read {config_file}: {exc}") from None
    return Path(start) if start and (Path(start) / PROVENANCE_FILE).is_file() else None


def check_fixed_tensors(loaded: LoadedPolicy, prior: Path | None = None) -> str:
    """Refuse unless only the posterior can depend on the certified demonstrations; say what was checked.

    Without `prior` the deterministic tensors must be the data-free reference (`freeze_deterministic`);
    with it, the prior tensors, the deterministic tensors and the normalisation statistics must be the
    prior checkpoint's.
    """
    network = loaded.policy.diffusion
    fixed = deterministic_tensors(network)
    if prior is None:
        run_prior = learned_prior_of_run(loaded.path)
        if run_prior is not None:
            raise CertificationError(
                f"{loaded.path} was fine-tuned from the learned prior {run_prior}: pass --prior={run_prior} so "
                "that its prior and its split are checked."
            )
        differences = tensor_differences(fixed, data_free_reference(loaded.policy.config))
        if differences:
            raise CertificationError(
                f"the deterministic tensors of {loaded.path} are not the data-free reference "
                f"({describe_differences(differences, len(fixed))}): they were trained on the demonstrations "
                "being certified, outside the KL, so no PAC-Bayes bound holds. Train with "
                "--policy.freeze_deterministic=true (or pass --prior if it was fine-tuned from a learned prior)."
            )
        return (
            f"deterministic tensors = the data-free reference (seed {REFERENCE_SEED}): {len(fixed)} checked; the "
            "normalisation statistics are the training dataset's meta/stats.json (not checked)"
        )
    prior_dir = resolve_pretrained_dir(prior)
    prior_state = _network_tensors(prior_dir / "model.safetensors")
    checks = (
        ("prior tensors (prior means and prior rho)", prior_tensors(network), prior_state),
        ("deterministic tensors", fixed, prior_state),
        ("normalisation statistics", _processor_tensors(loaded.path), _processor_tensors(prior_dir)),
    )
    for what, actual, reference in checks:
        differences = tensor_differences(actual, reference)
        if differences:
            raise CertificationError(
                f"the {what} of {loaded.path} are not those of the prior {prior_dir} "
                f"({describe_differences(differences, len(actual))}). Certify the checkpoint with the prior it "
                "was fine-tuned from, fine-tuned with freeze_deterministic=true on the same dataset."
            )
    return f"prior, deterministic tensors and normalisation = those of the prior {prior_dir}"


def check_held_out_is_unseen(pretrained_dir: Path, split: EpisodeSplit, root: Path | None) -> None:
    """The held-out bound needs demonstrations the checkpoint never trained on (train_config.json says which)."""
    if split.heldout_episodes and (pretrained_dir / "train_config.json").is_file():
        trained = split_from_train_config(pretrained_dir, root).train_episodes
        overlap = sorted(set(split.heldout_episodes) & set(trained))
        if overlap:
            raise MetricsError(
                f"--test_episodes includes {len(overlap)} demonstrations the checkpoint was trained on "
                f"({_preview(overlap)}; its train_config.json trains on {len(trained)} episodes, "
                f"{_preview(trained)}): a held-out bound on them would be invalid. Choose unseen episodes, or "
                "leave --test_episodes unset for the run's held-out split."
            )
    both = sorted(set(split.train_episodes) & set(split.heldout_episodes))
    if both:
        raise MetricsError(
            f"{len(both)} demonstrations are both certified and held out ({_preview(both)}); the held-out bound "
            "needs unseen ones. Make --train_episodes and --test_episodes disjoint."
        )


@dataclass(frozen=True)
class CertificateReport:
    checkpoint: str
    clip: float
    seed: int
    fixed_tensors: str  # what the non-posterior tensors were checked against
    train_episodes: list[int]
    pac_bayes: PacBayesCertificate
    train_risk_mean_network: float
    heldout_episodes: list[int] = field(default_factory=list)
    held_out: HeldOutCertificate | None = None

    def summary(self) -> str:
        pb, clip = self.pac_bayes, f"{self.clip:g}"
        lines = [
            f"PAC-Bayes certificate for {self.checkpoint} (loss: per-demo mean of min(MSE, {clip}) / {clip})",
            f"  checked: {self.fixed_tensors}",
            f"  N = {pb.num_demos} demonstrations, m = {pb.num_weight_samples} weight samples, KL(Q||P) = {pb.kl:.6g}",
            f"  empirical risk of Q (Monte Carlo) R_m             = {pb.empirical_risk:.5f}"
            f"   (posterior mean: {self.train_risk_mean_network:.5f})",
            f"  stage 1 kl^-1(R_m, ln(2/delta')/m)                = {pb.stage1:.5f}",
            f"  stage 2 kl^-1(stage 1, (KL+ln(2 sqrt(N)/delta))/N) = {pb.stage2:.5f}"
            f"   <- certificate, w.p. >= {pb.confidence:.3f}",
            f"  stage 2 at R_m itself                             = {pb.stage2_at_empirical_risk:.5f}"
            f"   (stage 1's share of the certificate: {pb.stage1_share:.5f})",
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
    if loaded.policy_type != "pacdp" or not getattr(loaded.policy.config, "bayesian", True):
        raise UnsupportedPolicyError(
            f"{loaded.path} is a {loaded.policy_type!r} policy without a posterior: a PAC-Bayes certificate needs "
            "the posterior and prior of a Bayesian 'pacdp' checkpoint. Build one from it with "
            "`pacdp-learned-prior` and fine-tune."
        )


def certify(
    loaded: LoadedPolicy,
    train_data: EvaluationData,
    heldout_data: EvaluationData | None = None,
    *,
    prior: Path | None = None,
    clip: float = 1.0,
    num_weight_samples: int = DEFAULT_WEIGHT_SAMPLES,
    delta: float | None = None,
    delta_prime: float = 0.01,
    seed: int = 0,
    batch_size: int = 256,
    progress: bool = True,
) -> CertificateReport:
    """Certify a PAC-DP checkpoint on its training demonstrations (and bound its mean network on held-out ones).

    Refuses (`CertificationError`) unless only the posterior depends on the demonstrations (`check_fixed_tensors`).
    """
    require_pacdp(loaded)
    if not clip > 0 or num_weight_samples < 1:
        raise MetricsError(f"need clip > 0 and num_weight_samples >= 1, got {clip} and {num_weight_samples}")
    fixed = check_fixed_tensors(loaded, prior)
    policy = loaded.policy
    delta = policy.config.delta if delta is None else delta
    kl = exact_kl(policy.unet)
    desc = "certified demos" if progress else None
    train = certification_windows(loaded, train_data, seed, batch_size, desc=desc)
    trivial = per_demo_means(trivial_losses(train, clip), train.episode.cpu()).mean().item()
    risks = monte_carlo_risks(policy, train, clip, num_weight_samples, seed, progress)
    held_out = None
    if heldout_data is not None:
        held = certification_windows(loaded, heldout_data, seed, batch_size, desc="held-out demos" if progress else None)
        held_out = held_out_certificate(
            per_demo_means(clipped_losses(policy, held, clip, batch_size=batch_size), held.episode.cpu()).tolist(),
            delta,
            per_demo_means(trivial_losses(held, clip), held.episode.cpu()).mean().item(),
        )
    return CertificateReport(
        checkpoint=str(loaded.path),
        clip=clip,
        seed=seed,
        fixed_tensors=fixed,
        train_episodes=train_data.episodes,
        pac_bayes=pac_bayes_certificate(risks.tolist(), kl, train.num_demos, delta, delta_prime, trivial),
        train_risk_mean_network=per_demo_means(
            clipped_losses(policy, train, clip, batch_size=batch_size), train.episode.cpu()
        ).mean().item(),
        heldout_episodes=heldout_data.episodes if heldout_data is not None else [],
        held_out=held_out,
    )


@dataclass
class CertifyConfig:
    """`pacdp-certify`: PAC-Bayes certificate of one PAC-DP checkpoint."""

    checkpoint: Path | None = None  # .../checkpoints/<step>/pretrained_model
    dataset: DatasetArgs = field(default_factory=DatasetArgs)
    # Demonstrations Q was trained on (certified); default: the run's training split. E.g. 70-199 or [70,71].
    train_episodes: EpisodeSelection | None = None
    # Unseen demonstrations for the posterior-mean bound; default: the run's eval_split ([] for none).
    test_episodes: EpisodeSelection | None = None
    clip: float = 1.0  # C: per-example MSE clipped at C, divided by C
    num_weight_samples: int = DEFAULT_WEIGHT_SAMPLES  # m (stage 1)
    delta: float | None = None  # default: the checkpoint's config.delta
    delta_prime: float = 0.01  # confidence of the Monte Carlo stage 1
    seed: int = 0  # per-example (t, eps) draws and the m weight samples
    batch_size: int = 256
    frame_stride: int = 1  # use every k-th window (in episode order)
    num_workers: int = 0  # DataLoader workers for the one-off read of the windows
    device: str | None = None
    output: Path | None = None  # write the report as JSON here
    # The pacdp-learned-prior checkpoint the run was fine-tuned from: its tensors and episodes are checked.
    prior: Path | None = None


def _certify_and_report(cfg: CertifyConfig) -> int:
    if cfg.checkpoint is None:
        raise MetricsError("pass --checkpoint=<.../checkpoints/<step>/pretrained_model>")
    loaded = load_policy(cfg.checkpoint, cfg.device)
    require_pacdp(loaded)
    train, test = (None if e is None else selected_episodes(e) for e in (cfg.train_episodes, cfg.test_episodes))
    split = resolve_split(loaded.path, cfg.dataset, train, test)
    check_held_out_is_unseen(loaded.path, split, cfg.dataset.root)
    if cfg.prior is not None:
        check_disjoint_from_prior(cfg.prior, split.train_episodes + split.heldout_episodes)
    config = loaded.policy.config

    def data(episodes: list[int]) -> EvaluationData:
        return EvaluationData(config, split.repo_id, split.root, episodes, cfg.frame_stride, cfg.num_workers)

    report = certify(
        loaded,
        data(split.train_episodes),
        data(split.heldout_episodes) if split.heldout_episodes else None,
        prior=cfg.prior,
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
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("pacdp-certify", CertifyConfig, _certify_and_report, argv)


if __name__ == "__main__":
    sys.exit(main())
