"""AUROC, the split-conformal threshold and the online alarm (`lerobot_pacdp.failure_prediction`) on hand-built cases."""

import math

import numpy as np
import pytest

from lerobot_pacdp.failure_prediction import (
    SignalTrace,
    auroc,
    auroc_interval,
    conformal_detection,
    conformal_threshold,
    episode_score,
    first_alarm_step,
    predict_failures,
    roc_curve,
    trailing_mean,
)


def _trace(success: bool, values: list[float], length: int = 400, every: int = 8) -> SignalTrace:
    return SignalTrace(success, length, np.arange(len(values)) * every, np.asarray(values, dtype=float))


def test_auroc_counts_the_pairs_a_failure_outscores_and_half_the_ties():
    # pairs (3,1) (3,2) (2,1) win, (2,2) ties: 3.5 of 4
    assert auroc([3.0, 2.0], [1.0, 2.0]) == 0.875
    assert auroc([5.0, 6.0], [1.0, 2.0]) == 1.0 and auroc([1.0], [2.0, 3.0]) == 0.0
    with pytest.raises(ValueError, match="both classes"):
        auroc([], [1.0])


def test_the_roc_curve_runs_from_the_origin_to_one_and_its_area_is_the_auroc():
    failed, succeeded = [0.9, 0.7, 0.4, 0.35], [0.8, 0.3, 0.2, 0.1, 0.05]
    fpr, tpr = roc_curve(failed, succeeded)
    assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0.0, 0.0, 1.0, 1.0)
    area = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
    assert area == pytest.approx(auroc(failed, succeeded)) == pytest.approx(17 / 20)


def test_the_bootstrap_interval_brackets_the_auroc_and_is_a_point_when_the_classes_never_overlap():
    failed, succeeded = [0.9, 0.7, 0.4, 0.35, 0.6], [0.8, 0.3, 0.2, 0.1, 0.05]
    low, high = auroc_interval(failed, succeeded, resamples=500)
    assert low < auroc(failed, succeeded) < high
    assert auroc_interval([5.0, 6.0], [1.0, 2.0], resamples=50) == (1.0, 1.0)


def test_the_conformal_threshold_is_the_ceil_n_plus_one_times_one_minus_alpha_smallest_score():
    scores = [5.0, 1.0, 4.0, 2.0, 3.0]
    assert conformal_threshold(scores, 0.2) == 5.0  # rank ceil(6 * 0.8) = 5
    assert conformal_threshold(scores, 0.5) == 3.0  # rank 3
    assert conformal_threshold(scores, 0.1) == math.inf  # rank 6 > 5: no threshold keeps the guarantee
    with pytest.raises(ValueError, match="alpha"):
        conformal_threshold(scores, 1.0)


def test_the_score_is_the_largest_trailing_mean_before_the_horizon_and_the_alarm_its_first_crossing():
    assert trailing_mean(np.array([1.0, 2.0, 3.0, 4.0]), 2).tolist() == [1.0, 1.5, 2.5, 3.5]
    trace = _trace(False, [0.1, 0.5, 0.9])  # decisions at steps 0, 8, 16
    assert episode_score(trace, horizon=16) == 0.5  # the decision at step 16 is not before the horizon
    assert episode_score(trace, horizon=17) == 0.9
    assert episode_score(trace, horizon=16, window=2) == pytest.approx(0.3)
    assert first_alarm_step(trace, 0.2, horizon=16) == 8
    assert first_alarm_step(trace, 0.6, horizon=16) is None and first_alarm_step(trace, 0.6, horizon=17) == 16


def test_conformal_detection_on_successes_that_all_score_alike():
    successes = [_trace(True, [1.0, 1.0], length=40) for _ in range(10)]
    failures = [_trace(False, [0.5, 2.0]) for _ in range(4)] + [_trace(False, [0.5, 0.5])]
    result = conformal_detection(successes + failures, alpha=0.2, horizon=40, splits=7)
    # every split's threshold is 1.0; held-out successes equal it (no alarm); 4 of 5 failures pass it at step 8
    assert result.threshold_median == 1.0 and result.calibration_size == 5 and result.splits == 7
    assert result.false_alarm_rate == 0.0 and result.detection_rate == pytest.approx(0.8)
    assert result.median_alarm_step == 8 and result.median_lead_steps == 392


def test_conformal_detection_refuses_too_few_successes_or_no_failures():
    with pytest.raises(ValueError, match="calibrate and to test"):
        conformal_detection([_trace(True, [1.0]), _trace(False, [2.0])], alpha=0.1, horizon=8)
    with pytest.raises(ValueError, match="needs failed episodes"):
        conformal_detection([_trace(True, [1.0])] * 4, alpha=0.1, horizon=8)


def test_every_episode_is_scored_on_the_shortest_episodes_steps_by_default():
    # failures run long and only rise late; scored on the first 16 steps they look like the successes
    successes = [_trace(True, [0.2, 0.2], length=16) for _ in range(4)]
    failures = [_trace(False, [0.2, 0.2, 5.0]) for _ in range(3)]
    prediction = predict_failures(successes + failures, splits=3)
    assert prediction.horizon == 16 and prediction.auroc == 0.5
    assert (prediction.n_episodes, prediction.n_failures) == (7, 3)
    assert predict_failures(successes + failures, horizon=400, splits=3).auroc == 1.0
