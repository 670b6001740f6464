"""PAC-DP inside LeRobot's own machinery: plugin discovery and the policy factory."""

import logging
import subprocess
import sys
from importlib.metadata import distribution

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_policy, make_pre_post_processors

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import make_tiny_dataset


def test_lerobot_discovers_the_plugin_from_the_installed_distribution_with_no_flag():
    assert distribution("lerobot_policy_pacdp").metadata["Name"] == "lerobot_policy_pacdp"
    script = (
        "import sys\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "assert 'pacdp' not in PreTrainedConfig.get_known_choices()\n"
        "register_third_party_plugins()\n"
        "assert 'pacdp' in PreTrainedConfig.get_known_choices(), PreTrainedConfig.get_known_choices()\n"
        "assert 'robosuite' not in sys.modules, 'plugin import must stay light'\n"
        "from lerobot.policies.factory import get_policy_class\n"
        "print(get_policy_class('pacdp').__module__)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip() == "lerobot_pacdp.modeling_pacdp"


def test_factory_resolves_policy_and_processors_by_naming_convention():
    assert get_policy_class("pacdp") is PacdpPolicy
    assert PreTrainedConfig.get_choice_class("pacdp") is PacdpConfig


@pytest.fixture(scope="module")
def tiny_dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data") / "tiny"
    make_tiny_dataset(root, episode_lengths=[30, 40, 50, 60])
    return root


def _make(config: PacdpConfig, dataset: LeRobotDataset) -> PacdpPolicy:
    # Mirrors lerobot_train: the training dataset is a local of the caller of make_policy.
    return make_policy(cfg=config, ds_meta=dataset.meta)


def test_outside_lerobot_train_n_falls_back_to_the_training_windows_found_on_the_stack_and_warns(
    tiny_dataset_root, caplog
):
    dataset = LeRobotDataset("local/tiny", root=tiny_dataset_root, episodes=[1, 3])
    with caplog.at_level(logging.WARNING, logger="lerobot_pacdp.training_set"):
        policy = _make(PacdpConfig(device="cpu", down_dims=(16, 32), horizon=8), dataset)
    # Episodes of 40 and 60 frames; the sampler starts no window in the last drop_n_last_frames = 7 of each.
    assert policy.config.num_train_samples == (40 - 7) + (60 - 7)
    assert dataset.meta.total_frames == 180
    assert "--policy.num_train_samples" in caplog.text


def test_an_explicit_n_is_kept(tiny_dataset_root):
    dataset = LeRobotDataset("local/tiny", root=tiny_dataset_root)
    policy = _make(PacdpConfig(device="cpu", down_dims=(16, 32), horizon=8, num_train_samples=7), dataset)
    assert policy.config.num_train_samples == 7


def test_environment_state_is_normalized_by_the_pacdp_preprocessor(tiny_dataset_root):
    dataset = LeRobotDataset("local/tiny", root=tiny_dataset_root)
    config = PacdpConfig(device="cpu", down_dims=(16, 32), horizon=8)
    _make(config, dataset)
    preprocessor, _ = make_pre_post_processors(config, dataset_stats=dataset.meta.stats)
    frame = dataset[0]
    raw = frame["observation.environment_state"]
    processed = preprocessor({k: v for k, v in frame.items() if k.startswith(("observation", "action"))})
    env = processed["observation.environment_state"].squeeze(0)
    stats = dataset.meta.stats["observation.environment_state"]
    expected = 2 * (raw - torch.as_tensor(stats["min"])) / (torch.as_tensor(stats["max"]) - torch.as_tensor(stats["min"])) - 1
    assert torch.allclose(env, expected.float(), atol=1e-5)
