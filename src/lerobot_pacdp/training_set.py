"""Find N of paper Eq. 9: the number of samples PAC-DP actually trains on.

LeRobot's `make_policy` hands a policy only `dataset_meta`, which describes the whole dataset and
ignores `--dataset.episodes` and `--dataset.eval_split`. Each `LeRobotDataset` owns its metadata
object, though, so the training dataset is the one object on the caller's stack whose `.meta` *is*
the `dataset_meta` we were given; its `num_frames` counts the frames of the selected training
episodes only. That lookup is done once, at construction.
"""

import sys
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TrainingSetSize:
    num_frames: int
    num_episodes: int
    source: str  # how the count was obtained, for the log


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


def training_set_size(dataset_meta: Any) -> TrainingSetSize:
    """Frames and episodes of the training dataset built on `dataset_meta` (whole dataset if none is found)."""
    dataset = _find_dataset_owning(dataset_meta)
    if dataset is not None:
        return TrainingSetSize(int(dataset.num_frames), int(dataset.num_episodes), "training dataset")
    return TrainingSetSize(
        int(dataset_meta.total_frames),
        int(dataset_meta.total_episodes),
        "whole dataset (no training dataset object found; pass --policy.num_train_samples to override)",
    )
