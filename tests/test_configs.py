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


@pytest.mark.parametrize("path", [p for p in CONFIGS if "cpu" not in p.stem], ids=lambda p: p.stem)
def test_paper_configs_train_on_copy_padded_actions_as_chis_code_does(path):
    config = draccus.parse(config_class=TrainPipelineConfig, config_path=path, args=[])
    assert config.policy.do_mask_loss_for_padding is False and config.policy.use_ema
    assert config.policy.noise_scheduler_type == "DDIM" and config.policy.num_inference_steps == 10


def test_the_config_files_are_package_data_and_the_checkouts_configs_links_to_them():
    """An installed package (not only an editable checkout) finds them: the study presets read them from it."""
    import fnmatch
    import tomllib

    from lerobot_pacdp.cli_errors import UserInputError
    from lerobot_pacdp.config_files import CONFIGS_DIR, config_file, load_config_file

    root = Path(__file__).parents[1]
    assert Path(lerobot_pacdp.__file__).parent / "configs" == CONFIGS_DIR
    assert (root / "configs").resolve() == CONFIGS_DIR.resolve()
    globs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["lerobot_pacdp"]
    shipped = sorted(p.relative_to(CONFIGS_DIR.parent).as_posix() for p in CONFIGS_DIR.rglob("*.json"))
    assert len(shipped) == len(CONFIGS) and all(any(fnmatch.fnmatch(p, g) for g in globs) for p in shipped)
    assert load_config_file("pusht/pacdp_cpu.json")["policy"]["type"] == "pacdp"
    with pytest.raises(UserInputError, match="missing from the installed package"):
        config_file("pusht/nope.json")
