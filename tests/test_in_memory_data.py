"""The in-memory data path gives exactly LeRobot's samples, and lerobot-train gets it only where intended."""

import logging
from types import SimpleNamespace

import pytest
import torch
from lerobot.datasets import EpisodeAwareSampler
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from lerobot_pacdp import train_hooks
from lerobot_pacdp.in_memory_data import InMemoryStateDataset

from pacdp_testing import make_tiny_dataset, tiny_config

EPISODE_LENGTHS = [12, 5, 9, 20, 3]


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data") / "tiny"
    make_tiny_dataset(root, episode_lengths=EPISODE_LENGTHS)
    return root


def _dataset(root, episodes=None) -> LeRobotDataset:
    meta = LeRobotDataset("local/tiny", root=root).meta
    delta_timestamps = resolve_delta_timestamps(tiny_config(), meta)
    return LeRobotDataset("local/tiny", root=root, episodes=episodes, delta_timestamps=delta_timestamps)


def _assert_items_equal(ours: dict, theirs: dict) -> None:
    assert ours.keys() == theirs.keys()
    for key, value in theirs.items():
        if isinstance(value, torch.Tensor):
            assert ours[key].dtype == value.dtype and ours[key].shape == value.shape, key
            assert torch.equal(ours[key], value), key
        else:
            assert ours[key] == value, key


@pytest.mark.parametrize("episodes", [None, [1, 3, 4], [3]])
def test_every_item_equals_lerobots_item_windows_padding_and_task_included(dataset_root, episodes):
    dataset = _dataset(dataset_root, episodes)
    in_memory = InMemoryStateDataset(dataset)
    assert len(in_memory) == len(dataset) and in_memory.num_episodes == dataset.num_episodes
    for index in range(len(dataset)):
        _assert_items_equal(in_memory[index], dataset[index])
    # The windows reach past both episode ends somewhere, so copy padding and the masks are exercised.
    assert any(dataset[i]["action_is_pad"].any() for i in range(len(dataset)))
    assert any(dataset[i]["observation.state_is_pad"].any() for i in range(len(dataset)))


def test_batches_through_lerobots_sampler_equal_lerobots_batches(dataset_root):
    dataset = _dataset(dataset_root, [0, 2, 3])
    in_memory = InMemoryStateDataset(dataset)

    def batches(source):
        sampler = EpisodeAwareSampler(
            dataset.meta.episodes["dataset_from_index"],
            dataset.meta.episodes["dataset_to_index"],
            episode_indices_to_use=dataset.episodes,
            drop_n_last_frames=3,
            shuffle=True,
            seed=7,
            absolute_to_relative_idx=dataset.absolute_to_relative_idx,
        )
        return list(torch.utils.data.DataLoader(source, batch_size=4, sampler=sampler))

    ours, theirs = batches(in_memory), batches(dataset)
    assert len(ours) == len(theirs) == 8  # (12-3) + (9-3) + (20-3) = 32 windows, in batches of 4
    for a, b in zip(ours, theirs, strict=True):
        _assert_items_equal(a, b)


def _cfg(policy) -> SimpleNamespace:
    return SimpleNamespace(policy=policy)


def test_the_hook_sets_n_to_the_training_windows_and_serves_pacdp_from_memory(dataset_root, caplog):
    train, held_out = _dataset(dataset_root, [0, 1, 2]), _dataset(dataset_root, [3, 4])
    policy = tiny_config(num_train_samples=None, drop_n_last_frames=3)
    with caplog.at_level(logging.INFO, logger="lerobot_pacdp.train_hooks"):
        served, served_eval = train_hooks.prepare_training_datasets(_cfg(policy), train, held_out)
    assert policy.num_train_samples == (12 - 3) + (5 - 3) + (9 - 3)
    assert "N = 17 (3 episodes; training windows" in caplog.text
    assert isinstance(served, InMemoryStateDataset) and isinstance(served_eval, InMemoryStateDataset)
    assert served.source is train and served.meta is train.meta


def test_the_hook_keeps_an_explicit_n_and_leaves_other_policy_types_on_lerobots_path(dataset_root, monkeypatch):
    monkeypatch.delenv(train_hooks.IN_MEMORY_DATA_ENV, raising=False)
    train = _dataset(dataset_root)
    policy = tiny_config(num_train_samples=5)
    train_hooks.prepare_training_datasets(_cfg(policy), train, None)
    assert policy.num_train_samples == 5
    other = DiffusionConfig(device="cpu")
    served, _ = train_hooks.prepare_training_datasets(_cfg(other), train, None)
    assert served is train
    monkeypatch.setenv(train_hooks.IN_MEMORY_DATA_ENV, "1")  # what the study sets for LeRobot's diffusion
    served, _ = train_hooks.prepare_training_datasets(_cfg(other), train, None)
    assert isinstance(served, InMemoryStateDataset)
    monkeypatch.setenv(train_hooks.IN_MEMORY_DATA_ENV, "0")
    served, _ = train_hooks.prepare_training_datasets(_cfg(policy), train, None)
    assert served is train


def test_install_wraps_lerobot_trains_dataset_factory_once():
    calls = []
    module = SimpleNamespace(make_train_eval_datasets=lambda cfg: calls.append(cfg) or ("train", None))
    train_hooks.install(module)
    first = module.make_train_eval_datasets
    train_hooks.install(module)
    assert module.make_train_eval_datasets is first
    assert first(_cfg(None)) == ("train", None) and len(calls) == 1
