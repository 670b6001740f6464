"""Session fixtures of the metrics tests: one tiny dataset and four tiny runs, built once."""

from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from metrics_testing import EPISODE_LENGTHS, REPO_ID, make_run
from pacdp_testing import make_tiny_dataset


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> LeRobotDataset:
    return make_tiny_dataset(tmp_path_factory.mktemp("metrics_data") / "tiny", EPISODE_LENGTHS, repo_id=REPO_ID)


@pytest.fixture(scope="session")
def tiny_runs(tmp_path_factory, tiny_dataset) -> dict[str, Path]:
    """Two PAC-DP seeds, one BDP, one LeRobot-diffusion (DP) run, and a PAC-DP run trained with
    `freeze_deterministic` (the only kind `pacdp-certify` accepts with a data-free prior)."""
    base = tmp_path_factory.mktemp("runs")
    kinds = {"pacdp_s0": ("pacdp", 0), "pacdp_s1": ("pacdp", 1), "bdp_s0": ("bdp", 2), "dp_s0": ("diffusion", 3)}
    kinds["frozen_s0"] = ("pacdp_frozen", 4)
    return {name: make_run(base / name, tiny_dataset, kind, seed) for name, (kind, seed) in kinds.items()}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny networks on a shared 2-core machine run ~2x faster on one thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
