"""`pacdp-metrics`: NPE and NLL bound (and optionally success rate) of every checkpoint of lerobot-train runs.

Writes one row per run x checkpoint step (`metrics.csv`, `metrics.json`), plots of each metric against
the training step with one curve per method and a mean +- std band over its runs/seeds (paper Fig. 3:
`npe.png`, `nll_bound.png`, `nll_paper_compatible_bits.png`, `kl.png`, `success_rate.png`, all panels in
`training_dynamics.png`; `kl` is KL(Q||P) of pacdp checkpoints, empty for DP), and the paper's
summary statistic (`summary.json`, printed): per run the mean over its last 10 checkpoints, then mean +-
std (sample std, ddof=1) over the runs of a method.

    pacdp-metrics --runs=[outputs/pacdp_s0,outputs/pacdp_s1,outputs/dp_s0,outputs/dp_s1] --output_dir=outputs/metrics

Held-out episodes default to each run's own `--dataset.eval_split` episodes (from train_config.json);
methods default to DP / BDP (pacdp with kl_weight 0) / PAC-DP, or pass `--labels` (one per run).
Every checkpoint is evaluated on the same per-example draws (`--seed`), so curves differ by the
models only. Rows already in `metrics.json` with the same settings are reused (`--resume=false` recomputes).

Columns beyond the metrics: `npe_sem` is the NPE's standard error clustered by episode (overlapping
windows of one episode are not independent; `npe_sem_iid` treats them as if they were, `npe_clusters`
counts the episodes); the JSON rows keep the per-episode NPE sums, from which
`lerobot_pacdp.metrics.comparison.paired_npe_difference` gives the paired difference of two checkpoints.
The NLL bound is in nats/dim (`nll_bound`, `nll_baseline`) and bits/dim (`*_bits`);
`nll_paper_compatible_bits` is the paper-compatible estimate, NOT a bound (see `nll_bound`; only with every
diffusion step evaluated); `heldout_error_step0` is the held-out denoising error per dimension at diffusion
step 0 (the largest log-SNR), and the JSON rows keep it for every evaluated step (`heldout_error_per_step`).
"""

import csv
import io
import json
import logging
import math
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from lerobot.envs.configs import EnvConfig
from tqdm.auto import tqdm

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.bayesian_layers import exact_kl
from lerobot_pacdp.cli_errors import run_draccus_cli
from lerobot_pacdp.episodes import EpisodeSelection, selected_episodes
from lerobot_pacdp.metrics.checkpoints import LoadedPolicy, MetricsError, list_checkpoints, load_policy
from lerobot_pacdp.metrics.data import DatasetArgs, EvaluationData, resolve_split
from lerobot_pacdp.metrics.nll_bound import NATS_PER_BIT, NllAccumulator, NllBound, nll_step_errors
from lerobot_pacdp.metrics.noise_prediction import (
    EpisodeSums,
    MeanWithError,
    alphas_cumprod,
    noise_prediction_errors,
    policy_denoiser,
)

logger = logging.getLogger(__name__)

METRICS = {  # column -> axis label
    "npe": "noise prediction error",
    "nll_bound": "NLL bound (nats / dim)",
    "nll_paper_compatible_bits": "paper-compatible NLL, not a bound (bits / dim)",
    "kl": "KL(Q||P) (nats)",  # pacdp only: how far the posterior moved from the prior (Eq. 9's complexity)
    "success_rate": "success rate",
}
# Summarised like the plotted metrics; the bound in bits is the nats plot's right axis, not a plot of its own.
SUMMARY_METRICS = {**METRICS, "nll_bound_bits": "NLL bound (bits / dim)"}
CSV_COLUMNS = [
    "label", "run", "step", "checkpoint", "policy_type", "npe", "npe_sem", "npe_examples",
    "nll_bound", "nll_baseline", "nll_examples", "kl", "success_rate",
    "npe_sem_iid", "npe_clusters", "nll_bound_bits", "nll_baseline_bits", "nll_paper_compatible_bits",
    "heldout_error_step0",
]  # fmt: skip
# Bump when the rows change meaning: stored rows of another version are recomputed, not reused.
ROWS_VERSION = 2


@dataclass(frozen=True)
class CheckpointMetrics:
    npe_sums: EpisodeSums  # per-episode sums of the per-window NPE
    npe_iid: MeanWithError  # the NPE with the (optimistic) standard error of independent windows
    nll: NllBound | None

    @property
    def npe(self) -> MeanWithError:
        """The NPE with its standard error clustered by episode."""
        return self.npe_sums.mean_with_error()


def evenly_spaced_steps(num_timesteps: int, count: int | None) -> list[int]:
    """`count` diffusion steps spread over the schedule, both ends included (all of them for None)."""
    if count is None or count >= num_timesteps:
        return list(range(num_timesteps))
    if count < 2:
        raise MetricsError(f"nll_steps must be >= 2 (the trapezoid needs two log-SNRs), got {count}")
    return torch.linspace(0, num_timesteps - 1, count).round().long().unique().tolist()


@torch.no_grad()
def evaluate_checkpoint(
    loaded: LoadedPolicy,
    data: EvaluationData,
    seed: int = 0,
    batch_size: int = 256,
    nll: bool = True,
    nll_steps: Sequence[int] | None = None,
    desc: str | None = None,
) -> CheckpointMetrics:
    """NPE (paper Sec. IV; the posterior mean for pacdp) and the NLL bound of one checkpoint on `data`.

    One pass: each window's NPE at its own seeded (t, eps), and for windows whose whole action chunk is
    real, its error at each diffusion step of `nll_steps` (default: every step of the schedule).
    """
    policy = loaded.policy
    alpha_bar = alphas_cumprod(policy)
    steps = list(range(len(alpha_bar))) if nll_steps is None else list(nll_steps)
    accumulator = NllAccumulator(alpha_bar, steps, seed) if nll else None
    npe_errors, episodes = [], []
    for batch in data.batches(loaded, batch_size, desc=desc):
        denoiser = policy_denoiser(policy, batch.global_cond)
        npe_errors.append(
            noise_prediction_errors(denoiser, batch.actions, batch.valid, batch.index, alpha_bar, seed).cpu()
        )
        episodes.append(batch.episode.cpu())
        complete = batch.valid.all(dim=1)
        if accumulator is not None and complete.any():
            actions, index = batch.actions[complete], batch.index[complete]
            complete_denoiser = policy_denoiser(policy, batch.global_cond[complete])
            accumulator.add(nll_step_errors(complete_denoiser, actions, index, alpha_bar, steps, seed), actions, index)
    errors = torch.cat(npe_errors)
    return CheckpointMetrics(
        EpisodeSums.of(errors, torch.cat(episodes)),
        MeanWithError.of(errors),
        accumulator.result() if accumulator is not None else None,
    )


def method_label(loaded: LoadedPolicy) -> str:
    config = loaded.policy.config
    if loaded.policy_type == "diffusion" or not getattr(config, "bayesian", True):
        return "DP"
    return "BDP" if config.kl_weight == 0 else "PAC-DP"


@dataclass(frozen=True)
class RolloutOutcome:
    """What LeRobot's evaluation loop measures over one checkpoint's rollouts."""

    success_rate: float  # 0-1
    avg_max_reward: float  # mean of each episode's best reward; on PushT, Diffusion Policy's coverage score


@torch.no_grad()
def rollout_outcome(
    loaded: LoadedPolicy, env_cfg: EnvConfig, n_envs: int, n_episodes: int, seed: int
) -> RolloutOutcome:
    """Success rate and score of rollouts through LeRobot's own evaluation loop (which closes the envs it is
    given, so each checkpoint gets fresh ones).

    `seed` seeds the envs' resets (seeds `seed`, `seed` + 1, ...) and, as lerobot-eval's `set_seed` does, the
    random generators the policy draws its diffusion noise (and a pacdp sample's weights) from, so the same call
    gives the same rollouts; the caller's random state is restored afterwards."""
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.scripts.lerobot_eval import eval_policy_all
    from lerobot.utils.random_utils import seeded_context

    envs = make_env(env_cfg, n_envs=n_envs, use_async_envs=False)

    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg, loaded.policy.config)
    with seeded_context(seed):
        info = eval_policy_all(
            envs=envs,
            policy=loaded.policy,
            env_preprocessor=env_preprocessor,
            env_postprocessor=env_postprocessor,
            preprocessor=loaded.preprocessor,
            postprocessor=loaded.postprocessor,
            n_episodes=n_episodes,
            start_seed=seed,
        )
    return RolloutOutcome(info["overall"]["pc_success"] / 100.0, float(info["overall"]["avg_max_reward"]))


def _finite(values: list[float]) -> list[float]:
    return [v for v in values if v is not None and math.isfinite(v)]


def _mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; 0 for a single value)."""
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return mean, std


def summarize(rows: list[dict], last_k: int = 10) -> dict:
    """Paper Sec. IV's statistic: per run the mean of its last `last_k` checkpoints, then mean +- std over runs."""
    by_label_run: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        by_label_run[row["label"]][row["run"]].append(row)
    summary = {}
    for label, runs in by_label_run.items():
        summary[label] = {"runs": len(runs)}
        for metric in SUMMARY_METRICS:
            per_run = []
            for run_rows in runs.values():
                values = _finite([r.get(metric) for r in sorted(run_rows, key=lambda r: r["step"])])[-last_k:]
                if values:
                    per_run.append(sum(values) / len(values))
            if per_run:
                mean, std = _mean_std(per_run)
                summary[label][metric] = {"mean": mean, "std": std, "runs": len(per_run)}
    return summary


def format_summary(summary: dict, last_k: int) -> str:
    lines = [f"mean over the last {last_k} checkpoints, mean +- std over runs:"]
    for label, entry in summary.items():
        parts = [f"{name} {entry[m]['mean']:.4f} +- {entry[m]['std']:.4f}" for m, name in SUMMARY_METRICS.items() if m in entry]
        lines.append(f"  {label} ({entry['runs']} runs): " + "  |  ".join(parts))
    return "\n".join(lines)


def plot_metrics(rows: list[dict], output_dir: Path) -> list[Path]:
    """One PNG per metric with data, and all panels side by side (paper Fig. 3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    present = [m for m in METRICS if _finite([r.get(m) for r in rows])]
    colors = {label: f"C{i}" for i, label in enumerate(sorted({r["label"] for r in rows}))}  # same in every panel

    def draw(ax, metric: str) -> None:
        by_label: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
        for row in rows:
            if row.get(metric) is not None and math.isfinite(row[metric]):
                by_label[row["label"]][row["step"]].append(row[metric])
        for label, by_step in sorted(by_label.items()):
            steps = sorted(by_step)
            stats = [_mean_std(by_step[s]) for s in steps]
            ax.plot(steps, [m for m, _ in stats], marker="o", markersize=3, label=label, color=colors[label])
            ax.fill_between(
                steps, [m - s for m, s in stats], [m + s for m, s in stats], color=colors[label], alpha=0.2
            )
        baselines = _finite([row["nll_baseline"] for row in rows]) if metric == "nll_bound" else []
        if baselines:  # what a denoiser no better than the Gaussian gets
            ax.axhline(sum(baselines) / len(baselines), color="gray", linestyle="--", label="Gaussian baseline $h_G/d$")
        if metric == "nll_bound":
            bits = ax.secondary_yaxis("right", functions=(lambda n: n / NATS_PER_BIT, lambda b: b * NATS_PER_BIT))
            bits.set_ylabel("bits / dim")
        if metric == "kl" and all(v > 0 for r in rows if (v := r.get("kl")) is not None):
            ax.set_yscale("log")  # BDP's KL grows by orders of magnitude over PAC-DP's
        ax.set_xlabel("training step")
        ax.set_ylabel(METRICS[metric])
        ax.grid(alpha=0.3)
        ax.legend()

    written = []
    for metric in present:
        fig, ax = plt.subplots(figsize=(5, 4))
        draw(ax, metric)
        fig.tight_layout()
        written.append(output_dir / f"{metric}.png")
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)
    if present:
        fig, axes = plt.subplots(1, len(present), figsize=(5 * len(present), 4), squeeze=False)
        for ax, metric in zip(axes[0], present, strict=True):
            draw(ax, metric)
        fig.tight_layout()
        written.append(output_dir / "training_dynamics.png")
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)
    return written


@dataclass
class SweepConfig:
    """`pacdp-metrics` options (LeRobot-style `--flag=value`, lists as `--runs=[a,b]`; `--config_path=file.json`
    works too). `run_sweep(SweepConfig(...))` is the same from Python."""

    runs: list[Path] = field(default_factory=list)  # lerobot-train output dirs or single checkpoints
    labels: list[str] | None = None  # a method label per run (default: DP / BDP / PAC-DP)
    output_dir: Path = Path("outputs/metrics")
    dataset: DatasetArgs = field(default_factory=DatasetArgs)  # default: each run's dataset
    episodes: EpisodeSelection | None = None  # held-out episodes, [140,141] or 140-199 (default: each run's eval split)
    seed: int = 0  # the per-example draws of t and eps, and the rollouts' env seeds and policy noise
    batch_size: int = 256
    nll: bool = True  # false: NPE (and success rate) only
    nll_steps: int | None = None  # evaluate the NLL bound at this many diffusion steps (default: all)
    frame_stride: int = 1  # use every k-th held-out window (in episode order)
    num_workers: int = 0  # DataLoader workers for the (one-off, cached) read of the held-out windows
    last_k: int = 10  # summary: mean over each run's last k checkpoints
    device: str | None = None
    resume: bool = True  # reuse rows of metrics.json computed with the same settings
    # Success rate through LeRobot's evaluation, off unless an env is given (e.g. --env.type=pusht).
    env: EnvConfig | None = None
    eval_episodes: int = 50  # rollouts per checkpoint
    eval_batch_size: int = 10  # environments stepped in parallel


def _settings(cfg: SweepConfig) -> dict:
    """What a stored row depends on besides the checkpoint: rows are reused only if these match."""
    keys = ("seed", "nll", "nll_steps", "frame_stride", "eval_episodes")
    settings = {k: getattr(cfg, k) for k in keys}
    # Stored as earlier versions wrote it (a range as typed, a list comma-joined), so rows already written
    # (the committed results/ among them) are still reused.
    episodes = cfg.episodes if cfg.episodes is None or isinstance(cfg.episodes, str) else ",".join(map(str, cfg.episodes))
    env = None if cfg.env is None else repr(cfg.env)
    settings.update(episodes=episodes, dataset=str(cfg.dataset), env=env, rows_version=ROWS_VERSION)
    return settings


def _run_data(cfg: SweepConfig, loaded: LoadedPolicy, shared: dict[tuple, EvaluationData]) -> EvaluationData:
    """The run's held-out windows; runs with the same data and windowing share one (cached) object."""
    heldout = None if cfg.episodes is None else selected_episodes(cfg.episodes)
    split = resolve_split(loaded.path, cfg.dataset, [], heldout)
    if not split.heldout_episodes:
        raise MetricsError(f"the run of {loaded.path} held out no episodes (eval_split = 0); pass --episodes.")
    config = loaded.policy.config
    key = (
        split.repo_id,
        str(split.root),
        tuple(split.heldout_episodes),
        tuple(config.observation_delta_indices or ()),
        tuple(config.action_delta_indices or ()),
        getattr(config, "drop_n_last_frames", 0),
        tuple(sorted(config.input_features)),
    )
    if key not in shared:
        shared[key] = EvaluationData(
            config, split.repo_id, split.root, split.heldout_episodes, cfg.frame_stride, cfg.num_workers
        )
    return shared[key]


def run_sweep(cfg: SweepConfig) -> tuple[list[dict], dict]:
    """Evaluate every checkpoint of every run; write the tables, plots and summary into cfg.output_dir."""
    runs = [Path(r) for r in cfg.runs]
    if not runs:
        raise MetricsError("pass --runs=[<run dir>,...] (lerobot-train output directories or checkpoints)")
    labels = list(cfg.labels) if cfg.labels else [None] * len(runs)
    if len(labels) != len(runs):
        raise MetricsError(f"--labels has {len(labels)} entries for {len(runs)} runs; give one label per run.")
    checkpoints = {run: list_checkpoints(run) for run in runs}  # fail before any work on a bad run dir
    settings = _settings(cfg)
    stored = {}
    previous_file = cfg.output_dir / "metrics.json"
    if cfg.resume and previous_file.is_file():
        previous = json.loads(previous_file.read_text())
        if previous.get("settings") == settings:
            stored = {row["checkpoint"]: row for row in previous["rows"]}

    rows: list[dict] = []
    heldout_sets, shared_data = {}, {}
    for run, label in zip(runs, labels, strict=True):
        data = None
        for step, ckpt in tqdm(checkpoints[run], desc=f"{run.name}", unit="ckpt"):
            if str(ckpt) in stored:
                rows.append(stored[str(ckpt)] | {"label": label or stored[str(ckpt)]["label"]})
                continue
            loaded = load_policy(ckpt, cfg.device)
            if data is None:
                data = _run_data(cfg, loaded, shared_data)
                heldout_sets[str(run)] = data.episodes
            nll_steps = evenly_spaced_steps(len(alphas_cumprod(loaded.policy)), cfg.nll_steps)
            result = evaluate_checkpoint(
                loaded, data, cfg.seed, cfg.batch_size, cfg.nll, nll_steps, desc=f"step {step}"
            )
            row = checkpoint_row(result, label or method_label(loaded), run, step, loaded)
            row["success_rate"] = (
                rollout_outcome(loaded, cfg.env, cfg.eval_batch_size, cfg.eval_episodes, cfg.seed).success_rate
                if cfg.env
                else None
            )
            rows.append(row)
            _write_tables(rows, settings, cfg.output_dir)
    if len({tuple(v) for v in heldout_sets.values()}) > 1:
        logger.warning("the runs were evaluated on different held-out episodes; their curves are not paired.")
    _write_tables(rows, settings, cfg.output_dir)
    summary = summarize(rows, cfg.last_k)
    write_text_atomic(cfg.output_dir / "summary.json", json.dumps({"last_k": cfg.last_k, "methods": summary}, indent=2))
    plot_metrics(rows, cfg.output_dir)
    return rows, summary


def checkpoint_row(result: CheckpointMetrics, label: str, run: Path, step: int, loaded: LoadedPolicy) -> dict:
    """One metrics.json row (CSV_COLUMNS plus the per-episode and per-step lists), success rate left unset."""
    nll, sums = result.nll, result.npe_sums
    paper = nll.paper_compatible if nll else None
    return {
        "label": label,
        "run": str(run),
        "step": step,
        "checkpoint": str(loaded.path),
        "policy_type": loaded.policy_type,
        "npe": result.npe.mean,
        "npe_sem": result.npe.sem,
        "npe_examples": result.npe.n,
        "npe_sem_iid": result.npe_iid.sem,
        "npe_clusters": result.npe.clusters,
        "npe_episodes": list(sums.episodes),
        "npe_episode_sums": list(sums.sums),
        "npe_episode_counts": list(sums.counts),
        "nll_bound": nll.nats_per_dim if nll else None,
        "nll_baseline": nll.baseline_nats_per_dim if nll else None,
        "nll_bound_bits": nll.bits_per_dim if nll else None,
        "nll_baseline_bits": nll.baseline_bits_per_dim if nll else None,
        "nll_paper_compatible_bits": paper.bits_per_dim if paper else None,  # NOT a bound
        "nll_examples": nll.num_examples if nll else None,
        "nll_steps": nll.steps if nll else None,
        "heldout_error_per_step": nll.error_per_step if nll else None,
        "heldout_error_step0": nll.error_per_step[nll.steps.index(0)] if nll and 0 in nll.steps else None,
        "kl": exact_kl(loaded.policy.unet) if loaded.policy_type == "pacdp" and loaded.policy.config.bayesian else None,
    }


def _write_tables(rows: list[dict], settings: dict, output_dir: Path) -> None:
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: ("" if row.get(k) is None else row[k]) for k in CSV_COLUMNS} for row in rows)
    write_text_atomic(output_dir / "metrics.csv", table.getvalue())
    write_text_atomic(output_dir / "metrics.json", json.dumps({"settings": settings, "rows": rows}, indent=2))


def _report_sweep(cfg: SweepConfig) -> int:
    rows, summary = run_sweep(cfg)
    print(
        f"evaluated {len(rows)} checkpoints; wrote {cfg.output_dir}/metrics.csv, metrics.json, summary.json and plots"
    )
    print(format_summary(summary, cfg.last_k))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("pacdp-metrics", SweepConfig, _report_sweep, argv)


if __name__ == "__main__":
    sys.exit(main())
