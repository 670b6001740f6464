"""What a trained policy achieved: its success rate over rollouts with a 95% interval, and one summary file.

`lerobot-eval` writes `eval_info.json` (one row per episode with its seed and success; a rollout split over
several lerobot-eval processes on consecutive seed ranges gives one file each); the interval is
Wilson's score interval, which stays inside [0, 1] and is sensible at 0 or n successes (the normal
approximation is not). `pacdp-summarize-run` joins it with the checkpoint (policy, training steps) and the
held-out NPE from `pacdp-metrics` into the JSON the main job commits:

    pacdp-summarize-run --eval_info=[OUT/eval/part0/eval_info.json,OUT/eval/part1/eval_info.json] --checkpoint=OUT/train/checkpoints/last/pretrained_model \
        --metrics=OUT/metrics/metrics.json --task=lift --wall_time_s=812 --output=OUT/summary.json
"""

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli

Z_95 = 1.959963984540054  # standard normal quantile at 0.975


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson's score interval for a binomial proportion (95% by default)."""
    if n <= 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n > 0, got {successes} of {n}")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    low = 0.0 if successes == 0 else max(0.0, centre - half)  # exact at the ends (the two terms cancel)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


@dataclass(frozen=True)
class SuccessRate:
    successes: int
    n_episodes: int

    @property
    def rate(self) -> float:
        return self.successes / self.n_episodes

    @property
    def ci95(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.n_episodes)

    def __str__(self) -> str:
        low, high = self.ci95
        return (f"{100 * self.rate:.1f}% ({self.successes}/{self.n_episodes} episodes; "
                f"95% interval {100 * low:.1f}-{100 * high:.1f}%)")


@dataclass(frozen=True)
class EpisodeOutcome:
    """One rollout as `lerobot-eval` recorded it; seed and best reward are None where its layout has none."""

    success: bool
    seed: int | None
    max_reward: float | None


def episode_outcomes(*eval_infos: dict) -> list[EpisodeOutcome]:
    """Every episode of one or more `lerobot-eval` runs, whichever of LeRobot's two layouts each run wrote.

    LeRobot 0.6.1 writes outcomes per task (`per_task[i].metrics`: `successes`, `max_rewards`; episode k of a
    run is seeded `--seed + k`, so runs started at consecutive seed ranges never share a seed); single-env
    evaluations write `per_episode` rows with their seeds."""
    episodes = []
    for eval_info in eval_infos:
        if eval_info.get("per_episode"):
            episodes += [EpisodeOutcome(bool(row["success"]), row.get("seed"), row.get("max_reward"))
                         for row in eval_info["per_episode"]]
            continue
        for task in eval_info.get("per_task", []):
            metrics = task.get("metrics", {})
            successes = metrics.get("successes", [])
            rewards = metrics.get("max_rewards") or [None] * len(successes)
            episodes += [EpisodeOutcome(bool(s), None, r) for s, r in zip(successes, rewards, strict=True)]
    return episodes


def success_rate_of(*eval_infos: dict) -> SuccessRate:
    """The success rate over the episodes of one or more `lerobot-eval` runs; recorded seeds must be distinct."""
    episodes = episode_outcomes(*eval_infos)
    seeds = [episode.seed for episode in episodes if episode.seed is not None]
    if len(set(seeds)) != len(seeds):
        raise UserInputError(f"the {len(episodes)} episodes do not have distinct seeds; rerun lerobot-eval.")
    if not episodes:
        raise UserInputError("the evaluation has no episode outcomes; pass the eval_info.json lerobot-eval wrote.")
    return SuccessRate(sum(episode.success for episode in episodes), len(episodes))


def average_max_reward(*eval_infos: dict) -> float | None:
    """LeRobot's `avg_max_reward` pooled over runs: the mean over episodes of each episode's best reward.

    On PushT that reward is clip(coverage / 0.95, 0, 1), so this is Diffusion Policy's PushT score, which
    shows how close failed pushes came; None when an episode has no reward recorded."""
    rewards = [episode.max_reward for episode in episode_outcomes(*eval_infos)]
    if not rewards or None in rewards:
        return None
    return sum(rewards) / len(rewards)


@dataclass(frozen=True)
class RunSummary:
    task: str
    policy: str
    success_rate: float  # 0-1
    n_episodes: int
    successes: int
    ci95: tuple[float, float]
    avg_max_reward: float | None  # LeRobot's name; PushT's score
    heldout_npe: float | None
    heldout_npe_sem: float | None  # clustered by episode
    train_steps: int
    wall_time_s: float | None
    checkpoint: str


def describe_policy(config: dict) -> str:
    """A short label: the method (PAC-DP, BDP, DP twin, LeRobot's diffusion) and its PAC-Bayes settings."""
    if config.get("type") != "pacdp":
        return str(config.get("type"))
    if not config.get("bayesian", True):
        return "pacdp bayesian=false (DP twin)"
    method = "BDP" if config.get("kl_weight") == 0 else "PAC-DP"
    return f"pacdp {method} (kl_weight={config.get('kl_weight')}, prior_rho={config.get('prior_rho')})"


def _read_json(path: Path, what: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UserInputError(f"{path} does not exist; pass the {what}.") from None
    except json.JSONDecodeError as exc:
        raise UserInputError(f"{path} is not valid JSON ({exc.msg}); pass the {what}.") from None


def _training_step(checkpoint: Path) -> int:
    state = checkpoint.parent / "training_state" / "training_step.json"
    if state.is_file():
        return int(_read_json(state, "checkpoint's training state")["step"])
    return int(_read_json(checkpoint / "train_config.json", "checkpoint's train_config.json")["steps"])


def _heldout_npe(metrics: Path | None, checkpoint: Path) -> tuple[float | None, float | None]:
    if metrics is None:
        return None, None
    rows = _read_json(metrics, "metrics.json pacdp-metrics wrote").get("rows") or []
    mine = [row for row in rows if Path(row.get("checkpoint", "")).resolve() == checkpoint.resolve()] or rows[-1:]
    if not mine:
        raise UserInputError(f"{metrics} holds no rows; run pacdp-metrics on the checkpoint first.")
    row = mine[-1]
    return float(row["npe"]), (float(row["npe_sem"]) if row.get("npe_sem") is not None else None)


def summarize_run(
    eval_infos: list[Path], checkpoint: Path, task: str, metrics: Path | None = None, wall_time_s: float | None = None
) -> RunSummary:
    infos = [_read_json(path, "eval_info.json lerobot-eval wrote") for path in eval_infos]
    success = success_rate_of(*infos)
    config = _read_json(checkpoint / "config.json", "checkpoint directory (its pretrained_model)")
    npe, npe_sem = _heldout_npe(metrics, checkpoint)
    return RunSummary(
        task=task,
        policy=describe_policy(config),
        success_rate=success.rate,
        n_episodes=success.n_episodes,
        successes=success.successes,
        ci95=success.ci95,
        avg_max_reward=average_max_reward(*infos),
        heldout_npe=npe,
        heldout_npe_sem=npe_sem,
        train_steps=_training_step(checkpoint),
        wall_time_s=wall_time_s,
        checkpoint=str(checkpoint),
    )


@dataclass
class SummarizeRunConfig:
    """`pacdp-summarize-run` options."""

    eval_info: list[Path] = field(default_factory=list)  # lerobot-eval's eval_info.json, one per process
    checkpoint: Path | None = None  # the evaluated checkpoint's pretrained_model directory
    task: str = ""
    metrics: Path | None = None  # pacdp-metrics' metrics.json for the checkpoint (held-out NPE)
    wall_time_s: float | None = None
    output: Path | None = None  # the summary JSON to write


def _summarize_main(cfg: SummarizeRunConfig) -> int:
    if not cfg.eval_info or cfg.checkpoint is None or not cfg.task or cfg.output is None:
        raise UserInputError("pass --eval_info, --checkpoint, --task and --output.")
    summary = summarize_run(cfg.eval_info, cfg.checkpoint, cfg.task, cfg.metrics, cfg.wall_time_s)
    write_text_atomic(cfg.output, json.dumps(asdict(summary), indent=2) + "\n")
    print(f"success rate: {SuccessRate(summary.successes, summary.n_episodes)}")
    if summary.avg_max_reward is not None:
        print(f"average best reward per episode (LeRobot's avg_max_reward; on PushT the score): {summary.avg_max_reward:.3f}")
    if summary.heldout_npe is not None:
        print(f"held-out NPE (EMA posterior mean): {summary.heldout_npe:.4f}")
    print(f"summary: {cfg.output}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_draccus_cli("pacdp-summarize-run", SummarizeRunConfig, _summarize_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
