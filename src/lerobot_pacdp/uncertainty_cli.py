"""`pacdp-uncertainty`: does the posterior's disagreement predict that a rollout fails?

    # roll a checkpoint out (LeRobot's evaluation loop, sync envs), then analyse
    pacdp-uncertainty --checkpoint=outputs/lift/checkpoints/001000/pretrained_model --env.type=robomimic \
        --env.task=lift --n_episodes=100 --batch_size=5 --samples=8 --output_dir=outputs/uncertainty/pacdp
    # or analyse episodes recorded by `lerobot-eval ... --policy.uncertainty_samples=8` (several pool), with
    # the DP twin's episodes as a second baseline and the out-of-distribution check of the checkpoint
    pacdp-uncertainty --episodes=[outputs/eval_a,outputs/eval_b] --twin_episodes=[outputs/eval_dp] \
        --checkpoint=... --env.type=robomimic --env.task=lift --n_episodes=0 --ood_shifts=[0.05,0.1,0.2] \
        --output_dir=results/uncertainty

Rollouts write `rollouts/eval_info.json` and `rollouts/uncertainty.json` under `--output_dir` (kept if the
analysis then stops). The analysis writes `summary.json`, `uncertainty_over_time.png`, `roc.png` (and
`ood.png`). The episode score, the conformal alarm and their parameters are `failure_prediction`'s.
"""

import json
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from lerobot.envs.configs import EnvConfig

from lerobot_pacdp.atomic_io import staged_file, write_text_atomic
from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli
from lerobot_pacdp.failure_prediction import (
    FailurePrediction,
    SignalTrace,
    episode_score,
    predict_failures,
    roc_curve,
)
from lerobot_pacdp.uncertainty_episodes import (
    SIGNAL,
    UNCERTAINTY_FILE,
    EpisodeUncertainty,
    UncertaintyRecording,
    read_recording,
    write_recording,
)

ROLLOUTS_DIR = "rollouts"
POSTERIOR = "PAC-DP posterior spread"
NOISE = "PAC-DP noise spread (fixed weights)"
TWIN_NOISE = "DP twin noise spread"


@dataclass
class UncertaintyConfig:
    """`pacdp-uncertainty` options (LeRobot-style `--flag=value`, lists as `--episodes=[a,b]`)."""

    checkpoint: Path | None = None  # a pacdp checkpoint to roll out (needs --env.*) and for --ood_shifts
    env: EnvConfig | None = None
    episodes: list[Path] = field(default_factory=list)  # recordings to analyse (uncertainty.json or its directory)
    twin_episodes: list[Path] = field(default_factory=list)  # the DP twin's recordings: its noise spread is a baseline
    output_dir: Path = Path("outputs/uncertainty")
    task: str = ""  # the task's name in summary.json (default: --env.task)
    # Rollouts of --checkpoint
    n_episodes: int = 100  # 0: none (analyse --episodes only)
    batch_size: int = 5  # environments stepped together (sync)
    samples: int = 8  # K
    seed: int = 1000  # episode k is seeded seed + k, as lerobot-eval does
    device: str | None = None
    # Failure prediction (lerobot_pacdp.failure_prediction)
    horizon: int | None = None  # steps scored; default: the shortest episode's length
    window: int = 1  # decisions in the trailing mean (1: the maximum of the raw signal)
    alpha: float = 0.1
    calibration_fraction: float = 0.5
    splits: int = 100
    # Out-of-distribution check (robomimic): the object moved this far (m) from its sampled start
    ood_shifts: list[float] = field(default_factory=list)
    ood_states: int = 50  # starts per shift, seeded after the rollouts' seeds


def _check(cfg: UncertaintyConfig) -> None:
    rolls_out = cfg.checkpoint is not None and cfg.n_episodes > 0
    if not rolls_out and not cfg.episodes:
        raise UserInputError("pass --checkpoint=DIR with --env.type=... to roll out, or --episodes=[...] to analyse recordings.")
    if cfg.checkpoint is not None and cfg.env is None:
        raise UserInputError("--checkpoint needs the environment to roll out in: pass --env.type=... (e.g. --env.type=robomimic --env.task=lift).")
    if cfg.ood_shifts and (cfg.checkpoint is None or getattr(cfg.env, "type", None) != "robomimic"):
        raise UserInputError("--ood_shifts moves robomimic objects: pass it with --checkpoint and --env.type=robomimic.")
    if any(shift <= 0 for shift in cfg.ood_shifts):
        raise UserInputError(f"--ood_shifts must be positive distances in metres, got {cfg.ood_shifts}.")
    if cfg.samples < 2:
        raise UserInputError(f"--samples must be at least 2 (a spread needs two chunks), got {cfg.samples}.")
    if cfg.n_episodes < 0 or min(cfg.batch_size, cfg.window, cfg.splits, cfg.ood_states) < 1:
        raise UserInputError("--n_episodes must be >= 0 and --batch_size, --window, --splits, --ood_states >= 1.")
    if not 0.0 < cfg.alpha < 1.0 or not 0.0 < cfg.calibration_fraction < 1.0:
        raise UserInputError("--alpha and --calibration_fraction must lie strictly between 0 and 1.")
    if cfg.horizon is not None and cfg.horizon < 1:
        raise UserInputError(f"--horizon must be >= 1 step, got {cfg.horizon}.")


def _load(cfg: UncertaintyConfig):
    from lerobot_pacdp.metrics.checkpoints import load_policy

    loaded = load_policy(cfg.checkpoint, cfg.device)
    if loaded.policy_type != "pacdp":
        raise UserInputError(
            f"{loaded.path} holds a {loaded.policy_type!r} policy; pacdp-uncertainty rolls out pacdp checkpoints "
            "(PAC-DP, BDP or the bayesian=false DP twin)."
        )
    loaded.policy.config.uncertainty_samples = cfg.samples
    loaded.policy.config.pretrained_path = str(loaded.path)
    return loaded


def roll_out(cfg: UncertaintyConfig, loaded) -> Path:
    """`n_episodes` rollouts through LeRobot's own evaluation loop, uncertainty recorded; the recording's path."""
    import torch
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.scripts import lerobot_eval
    from lerobot.utils.random_utils import set_seed

    from lerobot_pacdp import eval_hooks

    eval_hooks.install(lerobot_eval)
    set_seed(cfg.seed)  # as lerobot-eval does
    envs = make_env(cfg.env, n_envs=cfg.batch_size, use_async_envs=False)
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(cfg.env, loaded.policy.config)
    with torch.no_grad(), eval_hooks.recording_episodes() as recorder:
        info = lerobot_eval.eval_policy_all(
            envs=envs, policy=loaded.policy, env_preprocessor=env_preprocessor, env_postprocessor=env_postprocessor,
            preprocessor=loaded.preprocessor, postprocessor=loaded.postprocessor, n_episodes=cfg.n_episodes,
            start_seed=cfg.seed,
        )
    rollouts = cfg.output_dir / ROLLOUTS_DIR
    write_text_atomic(rollouts / "eval_info.json", json.dumps(info, indent=2) + "\n")
    path = write_recording(rollouts / UNCERTAINTY_FILE, recorder.recording())
    print(f"rolled out {cfg.n_episodes} episodes: {path}")
    return path


def pooled(paths: Sequence[Path]) -> UncertaintyRecording:
    """Several recordings of one policy as one; their seeds must not repeat."""
    recordings = [read_recording(p) for p in paths]
    names = ", ".join(map(str, paths))
    if len({(r.samples, r.policy, r.checkpoint) for r in recordings}) > 1:
        raise UserInputError(f"the recordings {names} differ in checkpoint, policy or K; pool one policy's rollouts.")
    episodes = tuple(e for r in recordings for e in r.episodes)
    seeds = [e.seed for e in episodes if e.seed is not None]
    if len(set(seeds)) != len(seeds):
        raise UserInputError(f"the recordings {names} repeat episode seeds; pool only distinct rollouts.")
    first = recordings[0]
    return UncertaintyRecording(first.samples, first.n_action_steps, first.policy, first.checkpoint, episodes)


def traces(episodes: Sequence[EpisodeUncertainty], signal: str) -> list[SignalTrace]:
    """One signal ("posterior" or "noise") of each episode."""
    return [
        SignalTrace(e.success, e.length, np.asarray(e.decision_steps), np.asarray(getattr(e, signal), dtype=float))
        for e in episodes
    ]


@dataclass(frozen=True)
class Analysis:
    horizon: int
    signals: dict[str, list[SignalTrace]]
    predictions: dict[str, FailurePrediction]


def analyse(cfg: UncertaintyConfig, recording: UncertaintyRecording, twin: UncertaintyRecording | None) -> Analysis:
    """Failure prediction from each signal: PAC-DP's posterior and noise spreads, and the DP twin's noise spread."""
    named = [(NOISE, recording, "noise")]
    if recording.has_posterior:
        named.insert(0, (POSTERIOR, recording, "posterior"))
    if twin is not None:
        named.append((TWIN_NOISE, twin, "noise"))
    horizon = cfg.horizon or min(e.length for _, r, _ in named for e in r.episodes)
    signals, predictions = {}, {}
    for name, source, signal in named:
        signals[name] = traces(source.episodes, signal)
        try:
            predictions[name] = predict_failures(
                signals[name], horizon, cfg.window, cfg.alpha, cfg.calibration_fraction, cfg.splits, cfg.seed
            )
        except ValueError as exc:
            raise UserInputError(f"{name}: {exc} Roll out more episodes (recorded ones are kept).") from None
    return Analysis(horizon, signals, predictions)


def summary_of(cfg: UncertaintyConfig, recording: UncertaintyRecording, analysis: Analysis, ood: list | None) -> dict:
    main = analysis.predictions[next(iter(analysis.predictions))]  # the posterior spread, if there is one
    baseline = analysis.predictions[NOISE]
    twin = analysis.predictions.get(TWIN_NOISE)
    success_lengths = [e.length for e in recording.episodes if e.success]
    summary = {
        "task": cfg.task or getattr(cfg.env, "task", ""),
        "checkpoint": recording.checkpoint,
        "policy": recording.policy,
        "signal": SIGNAL,
        "samples": recording.samples,
        "n_episodes": main.n_episodes,
        "n_failures": main.n_failures,
        "seeds": [e.seed for e in recording.episodes],
        "success_length_median": float(np.median(success_lengths)) if success_lengths else None,
        "horizon": analysis.horizon,
        "window": cfg.window,
        "auroc": main.auroc if recording.has_posterior else None,
        "auroc_ci95": main.auroc_ci95 if recording.has_posterior else None,
        "baseline_auroc": baseline.auroc,
        "baseline_auroc_ci95": baseline.auroc_ci95,
        "dp_twin_auroc": None if twin is None else twin.auroc,
        "conformal_alpha": cfg.alpha,
        "false_alarm_rate": main.conformal.false_alarm_rate,
        "detection_rate": main.conformal.detection_rate,
        "median_detection_lead_steps": main.conformal.median_lead_steps,
        "signals": {name: asdict(p) for name, p in analysis.predictions.items()},
    }
    if ood is not None:
        from lerobot_pacdp.uncertainty_ood import compare_to_unshifted

        summary["ood"] = {"seeds": [cfg.seed + cfg.n_episodes, cfg.seed + cfg.n_episodes + cfg.ood_states - 1],
                          "by_shift": [asdict(c) for c in compare_to_unshifted(ood)]}
    return summary


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    with staged_file(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    _pyplot().close(fig)


def plot_over_time(analysis: Analysis, path: Path) -> None:
    """Each signal over the episode, successes and failures apart: every episode thin, medians thick."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(analysis.signals), figsize=(5.5 * len(analysis.signals), 4), squeeze=False)
    for ax, (name, signal_traces) in zip(axes[0], analysis.signals.items(), strict=True):
        for outcome, color in ((True, "C0"), (False, "C3")):
            group = [t for t in signal_traces if t.success == outcome]
            for t in group:
                ax.plot(t.steps, t.values, color=color, alpha=0.1, linewidth=0.8)
            steps = np.unique(np.concatenate([t.steps for t in group])) if group else np.array([])
            medians = [np.median([t.values[t.steps == s][0] for t in group if s in t.steps]) for s in steps]
            ax.plot(steps, medians, color=color, linewidth=2.2, label=f"{'successes' if outcome else 'failures'} ({len(group)}), median")
        ax.axvline(analysis.horizon, color="gray", linestyle="--", label=f"scored steps T = {analysis.horizon}")
        ax.set_xlabel("environment step of the decision")
        ax.set_ylabel("spread of K chunks (normalised action units)")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def plot_roc(analysis: Analysis, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 5))
    for name, signal_traces in analysis.signals.items():
        prediction = analysis.predictions[name]
        scores = [episode_score(t, prediction.horizon, prediction.window) for t in signal_traces]
        failed = [s for s, t in zip(scores, signal_traces, strict=True) if not t.success]
        succeeded = [s for s, t in zip(scores, signal_traces, strict=True) if t.success]
        fpr, tpr = roc_curve(failed, succeeded)
        ax.plot(fpr, tpr, label=f"{name}: AUROC {prediction.auroc:.2f}")
    ax.plot([0, 1], [0, 1], color="gray", linestyle=":")
    ax.set_xlabel("false-positive rate (successes flagged)")
    ax.set_ylabel("true-positive rate (failures flagged)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def plot_ood(results: list, path: Path) -> None:
    plt = _pyplot()
    kinds = [k for k in ("posterior", "noise") if getattr(results[0], k) is not None]
    fig, axes = plt.subplots(1, len(kinds), figsize=(5 * len(kinds), 4), squeeze=False)
    for ax, kind in zip(axes[0], kinds, strict=True):
        ax.boxplot([getattr(r, kind) for r in results], tick_labels=[f"{r.shift:.2f}" for r in results])
        ax.set_xlabel("object moved from its sampled start (m)")
        ax.set_ylabel(f"{kind} spread at the first decision")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)


def _format(summary: dict) -> str:
    lines = [f"{summary['n_episodes']} episodes, {summary['n_failures']} failures; scored steps T = {summary['horizon']}"]
    for name, p in summary["signals"].items():
        c, (low, high) = p["conformal"], p["auroc_ci95"]
        lines.append(
            f"  {name}: AUROC {p['auroc']:.3f} (95% {low:.2f}-{high:.2f}); conformal alpha {c['alpha']}: false alarms "
            f"{c['false_alarm_rate']:.3f}, detection {c['detection_rate']:.3f}"
        )
    for row in summary.get("ood", {}).get("by_shift", []):
        lines.append(
            f"  object moved {row['shift']:.2f} m: mean posterior spread {row['posterior_mean']}, noise spread "
            f"{row['noise_mean']:.4f}; AUROC vs unmoved: posterior {row['posterior_auroc']}, noise {row['noise_auroc']:.3f}"
        )
    return "\n".join(lines)


def _main(cfg: UncertaintyConfig) -> int:
    _check(cfg)
    loaded = _load(cfg) if cfg.checkpoint is not None else None
    recordings = ([roll_out(cfg, loaded)] if loaded is not None and cfg.n_episodes > 0 else []) + list(cfg.episodes)
    recording = pooled(recordings)
    twin = pooled(cfg.twin_episodes) if cfg.twin_episodes else None
    analysis = analyse(cfg, recording, twin)
    ood = None
    if cfg.ood_shifts:
        from lerobot_pacdp.uncertainty_ood import shifted_starts

        first = cfg.seed + cfg.n_episodes  # starts the rollouts did not use
        ood = shifted_starts(
            loaded.policy, loaded.preprocessor, cfg.env.task, cfg.env.robosuite_compat,
            range(first, first + cfg.ood_states), cfg.ood_shifts, cfg.samples, cfg.batch_size,
        )
    summary = summary_of(cfg, recording, analysis, ood)
    plot_over_time(analysis, cfg.output_dir / "uncertainty_over_time.png")
    plot_roc(analysis, cfg.output_dir / "roc.png")
    if ood is not None:
        plot_ood(ood, cfg.output_dir / "ood.png")
    write_text_atomic(cfg.output_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    print(_format(summary))
    print(f"summary: {cfg.output_dir / 'summary.json'}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("pacdp-uncertainty", UncertaintyConfig, _main, argv)


if __name__ == "__main__":
    sys.exit(main())
