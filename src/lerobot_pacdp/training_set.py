"""N of paper Eq. 9: the number of training windows LeRobot's sampler draws from.

LeRobot's `EpisodeAwareSampler` starts a window at every frame of the selected training episodes except
the last `drop_n_last_frames` of each, so N is its length, not the frame count. Eq. 9 is the paper's
training surrogate: these windows overlap and are not i.i.d., so N here sets the strength of the
regulariser, not the size of a sample a bound holds for (the certificate, `lerobot_pacdp.metrics`, counts
demonstrations instead).

`lerobot_pacdp.train_hooks` sets N this way inside `lerobot-train`, from the dataset it trains on. Outside
it, `PacdpPolicy` gets only the whole dataset's metadata, so `training_set_size` falls back to finding the
training dataset on the caller's stack (the object whose `.meta` *is* that metadata), with a warning.
"""

import logging
import sys
from dataclasses import dataclass
from typing import Any

from lerobot.datasets import EpisodeAwareSampler

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainingSetSize:
    num_windows: int  # N
    num_episodes: int
    source: str  # how the count was obtained, for the log


def training_windows(dataset: Any, drop_n_last_frames: int) -> TrainingSetSize:
    """The windows LeRobot's sampler draws from `dataset` (its selected episodes), as lerobot-train builds it."""
    sampler = EpisodeAwareSampler(
        dataset.meta.episodes["dataset_from_index"],
        dataset.meta.episodes["dataset_to_index"],
        episode_indices_to_use=dataset.episodes,
        drop_n_last_frames=drop_n_last_frames,
    )
    return TrainingSetSize(
        len(sampler),
        int(dataset.num_episodes),
        f"training windows: frames of the training episodes minus drop_n_last_frames={drop_n_last_frames} each",
    )


def _find_dataset_owning(dataset_meta: Any, max_depth: int = 64) -> Any | None:
    frame = sys._getframe(1)
    for _ in range(max_depth):
        if frame is None:
            return None
        for value in frame.f_locals.values():
            if getattr(value, "meta", None) is dataset_meta and hasattr(value, "num_frames"):
                return value
        frame = frame.f_back
    return None


def training_set_size(dataset_meta: Any, drop_n_last_frames: int) -> TrainingSetSize:
    """Fallback N when the policy is built outside lerobot-train with no `num_train_samples` (warns)."""
    dataset = _find_dataset_owning(dataset_meta)
    if dataset is not None:
        size = training_windows(dataset, drop_n_last_frames)
        how = "the training dataset found on the caller's stack"
    else:
        size = TrainingSetSize(
            int(dataset_meta.total_frames), int(dataset_meta.total_episodes), "all frames of the whole dataset"
        )
        how = "the whole dataset (no training dataset object found)"
    logger.warning(
        "PAC-DP: num_train_samples was not given; N = %d was derived from %s. "
        "Pass --policy.num_train_samples=<training windows> to set it explicitly.",
        size.num_windows,
        how,
    )
    return size
