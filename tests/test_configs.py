"""Every file in configs/ is a valid `lerobot-train --config_path` file with the paper's PAC-DP settings."""

from pathlib import Path

import draccus
import pytest
from lerobot.configs.train import TrainPipelineConfig

import lerobot_pacdp  # noqa: F401  (registers the pacdp type, as LeRobot's plugin discovery does)
from lerobot_pacdp.configuration_pacdp import PacdpConfig

CONFIGS = sorted((Path(__file__).parents[1] / "configs").rglob("*.json"))


def test_there_are_config_files():
    assert any(p.parent.name == "pusht" for p in CONFIGS)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(p.parents[1])))
def test_config_parses_as_a_train_pipeline_config(path):
    config = draccus.parse(config_class=TrainPipelineConfig, config_path=path, args=[])
    assert isinstance(config.policy, PacdpConfig)
    assert config.policy.prior_rho == -4.5
    assert config.policy.kl_weight in (1e-4, 1e-5, 1e-6)


def test_pusht_paper_config_holds_the_paper_settings():
    config = draccus.parse(config_class=TrainPipelineConfig, config_path=Path(__file__).parents[1] / "configs/pusht/pacdp_paper.json", args=[])
    assert config.policy.kl_weight == 1e-4 and config.policy.down_dims == (256, 512, 1024)
    assert config.dataset.episodes == list(range(200)) and config.dataset.eval_split == 0.3  # 140 / 60 demos
    assert config.steps == 1_000_000 and config.save_freq == 5000
