"""Honest intervals for "checkpoint A has a lower held-out NPE than checkpoint B".

`pacdp-metrics` evaluates every checkpoint on the same windows with the same seeded (t, eps) draws, so
the per-window errors of two checkpoints are paired: the difference of their means has a far smaller
standard error than either mean. Episodes are the independent units (see `EpisodeSums`).
"""

from lerobot_pacdp.metrics.checkpoints import MetricsError
from lerobot_pacdp.metrics.noise_prediction import EpisodeSums, MeanWithError

_KEYS = ("npe_episodes", "npe_episode_sums", "npe_episode_counts")


def npe_episode_sums(row: dict) -> EpisodeSums:
    """The per-episode NPE sums stored in a `pacdp-metrics` row (metrics.json)."""
    if any(row.get(key) is None for key in _KEYS):
        raise MetricsError(
            f"the row of {row.get('checkpoint')} has no per-episode NPE sums; recompute it with this version "
            "of pacdp-metrics (--resume=false)."
        )
    return EpisodeSums(*(tuple(row[key]) for key in _KEYS))


def paired_npe_difference(row_a: dict, row_b: dict) -> MeanWithError:
    """NPE(a) - NPE(b) and its episode-clustered standard error, from two rows of one pacdp-metrics output.

    Rows of different outputs are paired only if they used the same --seed, --episodes and
    --frame_stride; the episodes and window counts are checked here, the seed is the caller's to keep.
    """
    try:
        return npe_episode_sums(row_a).minus(npe_episode_sums(row_b)).mean_with_error()
    except ValueError as exc:
        raise MetricsError(str(exc)) from None
