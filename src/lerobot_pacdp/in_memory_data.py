"""LeRobot's training samples of a state-only dataset, served from memory.

`LeRobotDataset.__getitem__` answers every sample with several Hugging Face dataset queries (the frame,
then one per windowed key); on a state-only dataset that costs more than the training step itself.
Diffusion Policy keeps such data in memory and indexes windows directly. `InMemoryStateDataset` does the
same and returns exactly LeRobot's items: the same keys, dtypes and shapes, the same windows clamped to
the episode (copy padding) with the same `*_is_pad` masks, and the task string. Everything else (`meta`,
`episodes`, `num_frames`, ...) is the wrapped dataset's, so LeRobot's sampler (`--dataset.episodes`,
`drop_n_last_frames`, the eval split) is unchanged.

`lerobot_pacdp.train_hooks` puts it under `lerobot-train`; datasets with images, videos or language
columns keep LeRobot's own path (`unsupported_reason`).
"""

from typing import Any

import torch
from lerobot.datasets.feature_utils import get_delta_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from torch import Tensor


def unsupported_reason(dataset: Any) -> str | None:
    """Why `dataset` cannot be served from memory, or None if it can."""
    if not isinstance(dataset, LeRobotDataset):
        return f"{type(dataset).__name__} is not a single LeRobotDataset"
    if dataset.meta.camera_keys:
        return f"it has camera features {dataset.meta.camera_keys}"
    if dataset.meta.has_language_columns:
        return "it has language columns"
    return None


class InMemoryStateDataset(torch.utils.data.Dataset):
    """A state-only `LeRobotDataset` with every column held as one tensor (see the module docstring)."""

    def __init__(self, dataset: LeRobotDataset):
        reason = unsupported_reason(dataset)
        if reason is not None:
            raise ValueError(f"cannot serve this dataset from memory: {reason}")
        self.source = dataset
        rows = dataset.hf_dataset[:]  # through LeRobot's own torch transform: the per-item dtypes
        self.columns: dict[str, Tensor] = {key: torch.stack(values) for key, values in rows.items()}
        deltas = get_delta_indices(dataset.delta_timestamps, dataset.fps) if dataset.delta_timestamps else {}
        self.windows: dict[str, Tensor] = {key: torch.as_tensor(d, dtype=torch.long) for key, d in deltas.items()}
        episodes = dataset.meta.episodes
        episode_of_row = self.columns["episode_index"].long()
        # Row of the first frame of every episode present (the rows hold the selected episodes, in order).
        first_row = torch.full((len(episodes["dataset_from_index"]),), -1, dtype=torch.long)
        rows_idx = torch.arange(len(episode_of_row))
        first_row.scatter_reduce_(0, episode_of_row, rows_idx, reduce="amin", include_self=False)
        from_index = torch.as_tensor(episodes["dataset_from_index"], dtype=torch.long)
        to_index = torch.as_tensor(episodes["dataset_to_index"], dtype=torch.long)
        self._episode_start = from_index[episode_of_row]  # absolute index of each row's episode start
        self._episode_end = to_index[episode_of_row]  # exclusive
        self._episode_first_row = first_row[episode_of_row]
        self._task_names = [str(name) for name in dataset.meta.tasks.index]

    def __getattr__(self, name: str) -> Any:
        if name == "source":  # not set yet (e.g. while unpickling in a DataLoader worker)
            raise AttributeError(name)
        return getattr(self.source, name)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, index: int) -> dict:
        return self.__getitems__([index])[0]

    def __getitems__(self, indices: list[int]) -> list[dict]:
        """A batch of items, gathered with one indexing operation per key (the DataLoader's batched fetch)."""
        rows = torch.as_tensor(indices, dtype=torch.long)
        batch: dict[str, Tensor] = {key: column[rows] for key, column in self.columns.items()}
        absolute = self.columns["index"][rows].long()
        start, end = self._episode_start[rows], self._episode_end[rows]
        for key, deltas in self.windows.items():
            wanted = absolute[:, None] + deltas[None, :]
            clamped = torch.minimum(torch.maximum(wanted, start[:, None]), end[:, None] - 1)
            window_rows = self._episode_first_row[rows][:, None] + (clamped - start[:, None])
            batch[key] = self.columns[key][window_rows]
            batch[f"{key}_is_pad"] = (wanted < start[:, None]) | (wanted >= end[:, None])
        tasks = batch["task_index"].tolist()
        return [
            {**{key: values[i] for key, values in batch.items()}, "task": self._task_names[tasks[i]]}
            for i in range(len(indices))
        ]
