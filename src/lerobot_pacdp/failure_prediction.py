"""How well a per-decision signal predicts that a rollout fails: AUROC and a split-conformal alarm.

An episode's signal is one value per decision step. The detector is online: at decision j it looks at
the trailing mean of the last `window` values (1: the value itself) and raises an alarm when that exceeds
a threshold. The episode score is the largest trailing mean over the decisions made in the first `horizon`
steps, so "score > threshold" is exactly "an alarm before step `horizon`". Scoring every episode on the same
number of steps matters: a successful episode ends early, and a maximum over more decisions is larger.

The threshold follows the FIPER / FAIL-Detect protocol: split conformal prediction on successful rollouts
only. A random part of the successes calibrates it (the ceil((n + 1)(1 - alpha))-th smallest of their n
scores, so a new successful rollout raises a false alarm with probability <= alpha); the other successes
measure the false-alarm rate and the failures the detection rate. Rates are means over many random splits.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SignalTrace:
    """One episode: outcome, length in environment steps, and the signal at its decision steps."""

    success: bool
    length: int
    steps: np.ndarray  # (decisions,) environment step of each decision
    values: np.ndarray  # (decisions,)


@dataclass(frozen=True)
class ConformalDetection:
    alpha: float
    splits: int
    calibration_size: int  # successes calibrating each split
    threshold_median: float  # over splits (inf: too few successes for this alpha)
    false_alarm_rate: float  # on held-out successes, mean over splits
    detection_rate: float  # on failures, mean over splits
    median_alarm_step: float | None  # over the detected failures of all splits (None: none detected)
    median_lead_steps: float | None  # episode length - alarm step, likewise


@dataclass(frozen=True)
class FailurePrediction:
    horizon: int  # steps whose decisions enter the score
    window: int  # decisions in the trailing mean
    n_episodes: int
    n_failures: int
    auroc: float
    auroc_ci95: tuple[float, float]  # stratified bootstrap
    conformal: ConformalDetection


def auroc(positive: Sequence[float], negative: Sequence[float]) -> float:
    """P(a random positive scores above a random negative), ties counted half (the Mann-Whitney AUC)."""
    pos, neg = np.asarray(positive, dtype=float), np.asarray(negative, dtype=float)
    if pos.size == 0 or neg.size == 0:
        raise ValueError(f"AUROC needs both classes, got {pos.size} positives and {neg.size} negatives.")
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


def auroc_interval(
    positive: Sequence[float], negative: Sequence[float], resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """95% percentile interval of the AUROC under resampling each class with replacement."""
    pos, neg = np.asarray(positive, dtype=float), np.asarray(negative, dtype=float)
    rng = np.random.default_rng(seed)
    values = [auroc(rng.choice(pos, pos.size), rng.choice(neg, neg.size)) for _ in range(resamples)]
    low, high = np.quantile(values, [0.025, 0.975])
    return float(low), float(high)


def roc_curve(positive: Sequence[float], negative: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(false-positive rate, true-positive rate) of "score >= t" for every threshold t, from (0, 0) to (1, 1)."""
    pos, neg = np.asarray(positive, dtype=float), np.asarray(negative, dtype=float)
    thresholds = np.unique(np.concatenate([pos, neg]))[::-1]
    fpr = [0.0] + [float((neg >= t).mean()) for t in thresholds]
    tpr = [0.0] + [float((pos >= t).mean()) for t in thresholds]
    return np.asarray(fpr), np.asarray(tpr)


def conformal_threshold(calibration: Sequence[float], alpha: float) -> float:
    """The ceil((n + 1)(1 - alpha))-th smallest calibration score; inf when that rank exceeds n."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}.")
    scores = np.sort(np.asarray(calibration, dtype=float))
    rank = math.ceil((scores.size + 1) * (1.0 - alpha))
    return float(scores[rank - 1]) if rank <= scores.size else math.inf


def trailing_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last `window` values at each position (fewer at the start)."""
    cumulative = np.concatenate([[0.0], np.cumsum(values, dtype=float)])
    ends = np.arange(1, values.size + 1)
    starts = np.maximum(ends - window, 0)
    return (cumulative[ends] - cumulative[starts]) / (ends - starts)


def _scored(trace: SignalTrace, horizon: int, window: int) -> np.ndarray:
    smoothed = trailing_mean(trace.values, window)
    return smoothed[trace.steps < horizon]


def episode_score(trace: SignalTrace, horizon: int, window: int = 1) -> float:
    """The largest trailing mean over the decisions made before step `horizon`."""
    scored = _scored(trace, horizon, window)
    if scored.size == 0:
        raise ValueError(f"an episode has no decision before step {horizon}.")
    return float(scored.max())


def first_alarm_step(trace: SignalTrace, threshold: float, horizon: int, window: int = 1) -> int | None:
    """The step of the first decision before `horizon` whose trailing mean exceeds `threshold`, else None."""
    above = np.flatnonzero(_scored(trace, horizon, window) > threshold)
    return int(trace.steps[above[0]]) if above.size else None


def conformal_detection(
    traces: Sequence[SignalTrace], alpha: float, horizon: int, window: int = 1,
    calibration_fraction: float = 0.5, splits: int = 100, seed: int = 0,
) -> ConformalDetection:
    """Split-conformal alarm calibrated on successes (see the module docstring), over `splits` random splits."""
    successes = [t for t in traces if t.success]
    failures = [t for t in traces if not t.success]
    if not failures:
        raise ValueError("a detection rate needs failed episodes; these all succeeded.")
    calibration_size = round(calibration_fraction * len(successes))
    if not 1 <= calibration_size < len(successes):
        raise ValueError(
            f"split conformal needs successes both to calibrate and to test; {len(successes)} successes with "
            f"calibration_fraction {calibration_fraction} give {calibration_size} to calibrate."
        )
    success_scores = np.array([episode_score(t, horizon, window) for t in successes])
    failure_scores = np.array([episode_score(t, horizon, window) for t in failures])
    rng = np.random.default_rng(seed)
    thresholds, false_alarms, detections, alarm_steps, leads = [], [], [], [], []
    for _ in range(splits):
        order = rng.permutation(len(successes))
        threshold = conformal_threshold(success_scores[order[:calibration_size]], alpha)
        thresholds.append(threshold)
        false_alarms.append(float((success_scores[order[calibration_size:]] > threshold).mean()))
        detections.append(float((failure_scores > threshold).mean()))
        for trace in failures:
            step = first_alarm_step(trace, threshold, horizon, window)
            if step is not None:
                alarm_steps.append(step)
                leads.append(trace.length - step)
    return ConformalDetection(
        alpha=alpha,
        splits=splits,
        calibration_size=calibration_size,
        threshold_median=float(np.median(thresholds)),
        false_alarm_rate=float(np.mean(false_alarms)),
        detection_rate=float(np.mean(detections)),
        median_alarm_step=float(np.median(alarm_steps)) if alarm_steps else None,
        median_lead_steps=float(np.median(leads)) if leads else None,
    )


def predict_failures(
    traces: Sequence[SignalTrace], horizon: int | None = None, window: int = 1, alpha: float = 0.1,
    calibration_fraction: float = 0.5, splits: int = 100, seed: int = 0,
) -> FailurePrediction:
    """AUROC of the episode score against failure, and the conformal alarm; `horizon` defaults to the
    shortest episode's length, so every episode is scored on equally many steps."""
    if horizon is None:
        horizon = min(t.length for t in traces)
    failed = [episode_score(t, horizon, window) for t in traces if not t.success]
    succeeded = [episode_score(t, horizon, window) for t in traces if t.success]
    return FailurePrediction(
        horizon=horizon,
        window=window,
        n_episodes=len(traces),
        n_failures=len(failed),
        auroc=auroc(failed, succeeded),
        auroc_ci95=auroc_interval(failed, succeeded, seed=seed),
        conformal=conformal_detection(traces, alpha, horizon, window, calibration_fraction, splits, seed),
    )
