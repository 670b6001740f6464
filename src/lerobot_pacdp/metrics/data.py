"""Held-out (or training) examples exactly as a checkpoint saw them in training.

Frames are windowed with the policy's delta timestamps (`resolve_delta_timestamps`, as `make_dataset`
does), selected like lerobot-train's `EpisodeAwareSampler` (the last `drop_n_last_frames` frames of an
episode are never sampled) and normalised with the checkpoint's own saved preprocessor.
"""

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets import EpisodeAwareSampler
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.factory import make_train_eval_datasets, resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_IMAGES
from lerobot.utils.feature_utils import dataset_to_policy_features
from torch import Tensor
from tqdm.auto import tqdm

from lerobot_pacdp.in_memory_data import InMemoryStateDataset, unsupported_reason
from lerobot_pacdp.metrics.checkpoints import DatasetMismatchError, LoadedPolicy, MetricsError


@dataclass(frozen=True)
class EpisodeSplit:
    """Where a run's demonstrations live and which of them it trained on / held out."""

    repo_id: str
    root: Path | None
    train_episodes: list[int]
    heldout_episodes: list[int]


def split_from_train_config(pretrained_dir: Path, root: Path | None = None) -> EpisodeSplit:
    """The train / held-out episodes of the run that wrote `pretrained_dir/train_config.json`.

    Re-derived with LeRobot's own `make_train_eval_datasets` (the last ceil(n * eval_split) episodes per
    task are held out), so the metrics use exactly the episodes lerobot-train's `eval_loss` used. No
    episodes are held out when the run used `dataset.eval_split = 0`.
    """
    config_file = pretrained_dir / "train_config.json"
    if not config_file.is_file():
        raise MetricsError(
            f"{pretrained_dir} has no train_config.json to read the run's dataset and held-out split from; "
            "pass --dataset.repo_id, --dataset.root and --episodes explicitly."
        )
    try:  # LeRobot raises many exception types for an unparsable config or an unreachable dataset
        train_config = TrainPipelineConfig.from_pretrained(config_file)
        if root is not None:
            train_config.dataset.root = str(root)
        train_dataset, eval_dataset = make_train_eval_datasets(train_config)
    except Exception as exc:
        raise MetricsError(
            f"cannot rebuild the run's train / held-out split from {config_file}: {exc}. Pass --dataset.root "
            "(if the dataset moved) or the episodes explicitly."
        ) from None
    return EpisodeSplit(
        repo_id=train_config.dataset.repo_id,
        root=Path(train_config.dataset.root) if train_config.dataset.root else None,
        train_episodes=list(train_dataset.episodes or range(train_dataset.meta.total_episodes)),
        heldout_episodes=list(eval_dataset.episodes) if eval_dataset is not None else [],
    )


@dataclass
class DatasetArgs:
    """CLI overrides of where the demonstrations live (default: the run's dataset, from train_config.json)."""

    repo_id: str | None = None
    root: Path | None = None


def resolve_split(
    pretrained_dir: Path, dataset: DatasetArgs, train: list[int] | None, heldout: list[int] | None
) -> EpisodeSplit:
    """Explicit episodes win (`[]` selects none); whatever is missing (None) comes from the run's split."""
    run = None
    if train is None or heldout is None or dataset.repo_id is None:
        run = split_from_train_config(pretrained_dir, dataset.root)
    return EpisodeSplit(
        repo_id=dataset.repo_id or run.repo_id,
        root=dataset.root if dataset.root is not None else (run.root if run else None),
        train_episodes=list(train) if train is not None else run.train_episodes,
        heldout_episodes=list(heldout) if heldout is not None else run.heldout_episodes,
    )


def check_features(config: PreTrainedConfig, meta: LeRobotDatasetMetadata, where: str) -> None:
    """Every policy input/output must exist in the dataset with the same shape."""
    available = dataset_to_policy_features(meta.features)
    problems = []
    for key, feature in {**config.input_features, **config.output_features}.items():
        if key not in available:
            problems.append(f"{key!r} is missing")
        elif tuple(available[key].shape) != tuple(feature.shape):
            problems.append(
                f"{key!r} has shape {tuple(available[key].shape)}, the policy expects {tuple(feature.shape)}"
            )
    if problems:
        raise DatasetMismatchError(
            f"the dataset {where} does not match the policy: {'; '.join(problems)}. Evaluate the checkpoint on "
            "the dataset it was trained on (see `dataset` in its train_config.json)."
        )


@dataclass
class EvalBatch:
    """One batch, normalised: the inputs of the noise-prediction network and the per-example keys."""

    actions: Tensor  # (B, horizon, action_dim), normalised
    valid: Tensor  # (B, horizon) bool: True where the action is real (not copy-padded)
    global_cond: Tensor  # (B, cond_dim): the observation window the U-Net is conditioned on
    index: Tensor  # (B,) int64 global frame index: seeds the example's draws
    episode: Tensor  # (B,) int64 episode index


class EvaluationData:
    """Windowed frames of `episodes` of a LeRobotDataset, for one policy configuration.

    With `cache` (default: when the policy uses no images) the raw windows are read once and kept in
    memory, through `InMemoryStateDataset` when the dataset is state-only: LeRobot's windowed reads (~10-50
    ms a window on a CPU) dominate the cost of evaluating a state-based U-Net, and a sweep evaluates the same
    windows for every checkpoint.
    """

    def __init__(
        self,
        config: PreTrainedConfig,
        repo_id: str,
        root: Path | str | None,
        episodes: Sequence[int],
        frame_stride: int = 1,
        num_workers: int = 0,
        cache: bool | None = None,
    ):
        if frame_stride < 1:
            raise MetricsError(f"frame_stride must be >= 1, got {frame_stride}")
        episodes = sorted(set(episodes))
        if not episodes:
            raise MetricsError("no episodes selected for evaluation")
        where = f"{repo_id} at {root}" if root else repo_id
        try:
            meta = LeRobotDatasetMetadata(repo_id, root=root)
        except Exception as exc:  # LeRobot raises several types (hub, file, value) for a missing dataset
            raise MetricsError(f"cannot open the dataset {where}: {exc}") from None
        check_features(config, meta, where)
        missing = [e for e in episodes if not 0 <= e < meta.total_episodes]
        if missing:
            raise DatasetMismatchError(
                f"the dataset {where} has {meta.total_episodes} episodes; episodes {missing[:10]} do not exist."
            )
        self.config = config
        self.episodes = episodes
        self.dataset = LeRobotDataset(
            repo_id, root=root, episodes=episodes, delta_timestamps=resolve_delta_timestamps(config, meta)
        )
        sampler = EpisodeAwareSampler(
            self.dataset.meta.episodes["dataset_from_index"],
            self.dataset.meta.episodes["dataset_to_index"],
            episode_indices_to_use=episodes,
            drop_n_last_frames=getattr(config, "drop_n_last_frames", 0),
            absolute_to_relative_idx=self.dataset.absolute_to_relative_idx,
        )
        self.positions = sampler.indices[::frame_stride]
        self.num_workers = num_workers
        self.cache = not config.image_features if cache is None else cache
        self._windows: dict[str, Tensor] | None = None

    def __len__(self) -> int:
        return len(self.positions)

    def _loader(self, batch_size: int, in_memory: bool = False) -> torch.utils.data.DataLoader:
        dataset = InMemoryStateDataset(self.dataset) if in_memory else self.dataset
        return torch.utils.data.DataLoader(
            dataset, batch_size=batch_size, sampler=self.positions, num_workers=self.num_workers
        )

    def _raw_batches(self, batch_size: int) -> Iterator[dict]:
        if not self.cache:
            yield from self._loader(batch_size)
            return
        if self._windows is None:
            loader = self._loader(1024, in_memory=unsupported_reason(self.dataset) is None)
            chunks = list(tqdm(loader, desc="reading windows", leave=False))
            self._windows = {k: torch.cat([c[k] for c in chunks]) for k, v in chunks[0].items() if torch.is_tensor(v)}
        for start in range(0, len(self), batch_size):
            yield {key: value[start : start + batch_size] for key, value in self._windows.items()}

    def batches(self, loaded: LoadedPolicy, batch_size: int = 256, desc: str | None = None) -> Iterator[EvalBatch]:
        """Normalised batches with the U-Net's global conditioning computed by `loaded.policy`."""
        policy = loaded.policy
        raw_batches = self._raw_batches(batch_size)
        for raw in tqdm(
            raw_batches, desc=desc, total=math.ceil(len(self) / batch_size), leave=False, disable=desc is None
        ):
            batch = loaded.preprocessor(raw)
            if policy.config.image_features:  # as DiffusionPolicy.forward stacks the cameras
                batch[OBS_IMAGES] = torch.stack([batch[key] for key in policy.config.image_features], dim=-4)
            with torch.no_grad():
                global_cond = policy.diffusion._prepare_global_conditioning(batch)
            yield EvalBatch(
                actions=batch[ACTION],
                valid=~batch[f"{ACTION}_is_pad"],
                global_cond=global_cond,
                index=raw["index"].long(),
                episode=raw["episode_index"].long(),
            )
