"""The task table, the compat layouts, the env config and the config files (no simulator needed)."""

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np
import pytest
from lerobot.configs.train import TrainPipelineConfig
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import env_to_policy_features

import lerobot_pacdp  # noqa: F401  (registers pacdp and --env.type=robomimic, as plugin discovery does)
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.env_config import RobomimicEnvConfig, gym_id
from lerobot_pacdp.robomimic.tasks import TASKS, get_task, layout_names
from lerobot_pacdp.robomimic.train_configs import CPU_RECIPES, CPU_TASKS, expected_files

CONFIG_DIR = Path(__file__).parents[2] / "configs" / "robomimic"

# Diffusion Policy's low-dim observation sizes (object + eef pos/quat + gripper, per robot).
DP_OBS_DIMS = {"lift": 19, "can": 23, "square": 23, "tool_hang": 53, "transport": 59}


@pytest.mark.parametrize("name", list(DP_OBS_DIMS))
def test_task_dims_match_diffusion_policy(name):
    task = TASKS[name]
    assert task.obs_dim == DP_OBS_DIMS[name]
    assert task.action_dim == (14 if name == "transport" else 7)
    assert len(task.state_names) == task.state_dim and len(task.object_names) == task.object_dim
    assert len(task.action_names) == task.action_dim


def test_task_table_holds_the_paper_settings():
    assert {n: t.episode_length for n, t in TASKS.items()} == {
        "lift": 400, "can": 400, "square": 400, "transport": 700, "tool_hang": 700
    }
    assert {n: t.kl_weight for n, t in TASKS.items()} == {
        "lift": 1e-5, "can": 1e-5, "square": 1e-6, "transport": 1e-6, "tool_hang": 1e-5
    }
    assert {n: t.train_steps for n, t in TASKS.items()} == {
        "lift": 250_000, "can": 250_000, "square": 250_000, "transport": 500_000, "tool_hang": 500_000
    }
    assert TASKS["transport"].robots == ("Panda", "Panda")
    assert TASKS["transport"].env_configuration == "single-arm-opposed"
    assert {t.env_name for t in TASKS.values()} == {"Lift", "PickPlaceCan", "NutAssemblySquare", "TwoArmTransport", "ToolHang"}


def test_get_task_accepts_robosuite_names_and_rejects_others():
    assert get_task("PickPlaceCan") is TASKS["can"] and get_task("tool-hang") is TASKS["tool_hang"]
    with pytest.raises(ValueError, match="choose one of lift, can, square, transport, tool_hang"):
        get_task("stack")


def test_feature_names_say_which_slice_is_which():
    assert TASKS["lift"].object_names == [
        "cube_pos.x", "cube_pos.y", "cube_pos.z", "cube_quat.x", "cube_quat.y", "cube_quat.z", "cube_quat.w",
        "gripper_to_cube_pos.x", "gripper_to_cube_pos.y", "gripper_to_cube_pos.z",
    ]
    assert TASKS["transport"].state_names[9:12] == ["robot1_eef_pos.x", "robot1_eef_pos.y", "robot1_eef_pos.z"]
    assert TASKS["lift"].state_names[7:] == ["robot0_gripper_qpos.0", "robot0_gripper_qpos.1"]


# -- compat: the robosuite <= 1.4 layouts (differences 1-3) ----------------------------------------------
def _keys(layout):
    return [key for key, _ in layout]


def test_legacy_layout_of_per_object_tasks_puts_world_pose_first():
    assert _keys(compat.legacy_object_layout("can")) == ["Can_pos", "Can_quat", "Can_to_robot0_eef_pos", "Can_to_robot0_eef_quat"]
    assert _keys(TASKS["can"].object_layout) == ["Can_to_robot0_eef_pos", "Can_to_robot0_eef_quat", "Can_pos", "Can_quat"]
    legacy = _keys(compat.legacy_object_layout("tool_hang"))
    assert legacy[:4] == ["base_pos", "base_quat", "base_to_robot0_eef_pos", "base_to_robot0_eef_quat"]
    assert legacy[8:10] == ["tool_pos", "tool_quat"] and legacy[-2:] == ["frame_is_assembled", "tool_on_frame"]


def test_legacy_transport_layout_has_the_flags_last():
    native, legacy = _keys(TASKS["transport"].object_layout), _keys(compat.legacy_object_layout("transport"))
    assert native[8:10] == ["payload_in_target_bin", "trash_in_trash_bin"]
    assert legacy[-2:] == ["payload_in_target_bin", "trash_in_trash_bin"]
    assert sorted(native) == sorted(legacy)


@pytest.mark.parametrize("name", list(TASKS))
def test_object_translation_round_trips(name):
    vectors = np.random.default_rng(0).normal(size=(5, TASKS[name].object_dim))
    legacy = compat.object_to_legacy(name, vectors)
    np.testing.assert_array_equal(compat.object_from_legacy(name, legacy), vectors)
    # Every legacy slice holds the same observable as the native one (up to Lift's sign).
    native_slices, start = {}, 0
    for key, size in TASKS[name].object_layout:
        native_slices[key] = vectors[:, start : start + size]
        start += size
    start = 0
    for key, size in compat.legacy_object_layout(name):
        sign = -1.0 if (name, key) == ("lift", "gripper_to_cube_pos") else 1.0
        np.testing.assert_array_equal(legacy[:, start : start + size], sign * native_slices[key])
        start += size


def test_lift_relative_position_changes_sign_in_legacy_layout():
    native = np.arange(10.0)
    legacy = compat.object_to_legacy("lift", native)
    np.testing.assert_array_equal(legacy[:7], native[:7])
    np.testing.assert_array_equal(legacy[7:], -native[7:])


def test_object_translation_rejects_wrong_width():
    with pytest.raises(ValueError, match="14 entries"):
        compat.object_to_legacy("can", np.zeros(10))


@pytest.mark.parametrize(
    ("env_args", "repository_version", "expected"),
    [
        ({"env_version": "1.4.1"}, None, ("1.4", "1.4.1")),
        ({"env_version": "1.5.1"}, None, ("1.5", "1.5.1")),
        ({}, "1.2.0", ("1.4", "1.2.0")),
        ({"env_kwargs": {"controller_configs": {"type": "OSC_POSE"}}}, None, ("1.4", None)),
        ({"env_kwargs": {"controller_configs": {"type": "BASIC", "body_parts": {}}}}, None, ("1.5", None)),
    ],
)
def test_file_generation(env_args, repository_version, expected):
    assert compat.file_generation(env_args, repository_version) == expected


@pytest.mark.parametrize(("value", "expected"), [(1.4, "1.4"), ("1.4.1", "1.4"), ("<=1.4", "1.4"), ("1.2", "1.4"), ("1.5", "1.5"), (1.5, "1.5"), ("legacy", "1.4")])
def test_normalize_generation(value, expected):
    assert compat.normalize_generation(value) == expected


def test_normalize_generation_rejects_nonsense():
    with pytest.raises(ValueError, match="robosuite_compat must be '1.5'"):
        compat.normalize_generation("banana")


# -- the LeRobot env config ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(TASKS))
def test_env_config_features_give_the_policy_the_dataset_keys(name):
    task = TASKS[name]
    config = RobomimicEnvConfig(task=name)
    features = env_to_policy_features(config)
    assert {k: v.shape for k, v in features.items()} == {
        "action": (task.action_dim,),
        "observation.state": (task.state_dim,),
        "observation.environment_state": (task.object_dim,),
    }
    assert config.gym_kwargs["max_episode_steps"] == task.episode_length == config.episode_length
    assert config.fps == 20 and config.gym_id == gym_id(name) == f"pacdp_robomimic/{name}-v0"


@dataclass
class _EnvOnly:
    env: EnvConfig


def test_env_config_parses_from_the_command_line():
    args = ["--env.type=robomimic", "--env.task=transport", "--env.robosuite_compat=1.4"]
    config = draccus.parse(_EnvOnly, args=args).env
    assert isinstance(config, RobomimicEnvConfig)
    assert config.task == "transport" and config.robosuite_compat == "1.4" and config.episode_length == 700
    assert config.features["environment_state"].shape == (41,)


def test_env_config_rejects_unknown_tasks_and_compat_values():
    with pytest.raises(ValueError, match="not a robomimic task"):
        RobomimicEnvConfig(task="PushT-v0")
    with pytest.raises(ValueError, match="robosuite_compat"):
        RobomimicEnvConfig(task="lift", robosuite_compat="2.0-beta")


def test_importing_the_plugin_does_not_import_the_simulator():
    code = (
        "import sys, lerobot_pacdp\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "assert 'robomimic' in EnvConfig.get_known_choices()\n"
        "heavy = [m for m in ('robosuite', 'mujoco', 'h5py') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


# -- config files ----------------------------------------------------------------------------------------
def test_config_files_agree_with_the_task_table():
    """The files repeat the task table's values: they must be exactly what train_configs generates."""
    files = {p.name for p in CONFIG_DIR.glob("*.json")}
    assert files == set(expected_files()), "regenerate: python -m lerobot_pacdp.robomimic.train_configs"
    for name, content in expected_files().items():
        assert json.loads((CONFIG_DIR / name).read_text()) == content, name


def test_the_config_generator_is_a_draccus_command_writing_the_packaged_files(tmp_path, capsys):
    from lerobot_pacdp.config_files import CONFIGS_DIR
    from lerobot_pacdp.robomimic import train_configs

    assert train_configs.TrainConfigsConfig().output_dir == CONFIGS_DIR / "robomimic"
    assert train_configs.main([f"--output_dir={tmp_path}"]) == 0
    assert sorted(capsys.readouterr().out.split()) == sorted(str(tmp_path / name) for name in expected_files())
    assert all((tmp_path / name).read_text() == (CONFIG_DIR / name).read_text() for name in expected_files())
    with pytest.raises(SystemExit) as exited:  # an unknown flag: draccus' usage and error, as in LeRobot's CLIs
        train_configs.main(["--output_dirr=x"])
    assert exited.value.code == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last == "python -m lerobot_pacdp.robomimic.train_configs: error: unrecognized arguments: --output_dirr=x"


@pytest.mark.parametrize("name", list(TASKS))
def test_paper_config_parses_with_the_paper_settings(name):
    task = TASKS[name]
    config = draccus.parse(config_class=TrainPipelineConfig, config_path=CONFIG_DIR / f"{name}.json", args=[])
    assert isinstance(config.policy, PacdpConfig) and isinstance(config.env, RobomimicEnvConfig)
    assert config.policy.kl_weight == task.kl_weight and config.policy.prior_rho == -4.5
    assert config.steps == task.train_steps
    assert config.dataset.episodes == list(range(200)) and config.dataset.eval_split == 0.3  # 140 / 60 demos
    assert config.env.task == name and config.env.robosuite_compat == "1.4"
    assert config.policy.horizon == 16 and config.policy.n_obs_steps == 2 and config.policy.n_action_steps == 8


@pytest.mark.parametrize("name", CPU_TASKS)
def test_cpu_preset_parses_as_a_small_model_with_the_cpu_recipe(name):
    config = draccus.parse(config_class=TrainPipelineConfig, config_path=CONFIG_DIR / f"{name}_cpu.json", args=[])
    recipe = CPU_RECIPES[name]
    assert config.policy.down_dims == (32, 64, 128) and config.batch_size == 64 and config.steps == recipe.steps
    assert config.save_freq == config.eval_steps == recipe.save_freq
    # The recipe reaches lerobot-train's optimizer and scheduler presets (its lr, 100 warm-up steps).
    assert config.policy.get_optimizer_preset().lr == recipe.optimizer_lr
    assert config.policy.get_scheduler_preset().num_warmup_steps == 100
    assert config.policy.device == "cpu" and config.env.robosuite_compat == "1.5"
    assert config.policy.kl_weight == TASKS[name].kl_weight


def test_can_trains_longer_at_a_lower_rate_than_lift():
    """The measured recipes (results/recipes/{lift,can}): Lift 3000 steps at 6e-3, Can 20000 at 3e-3."""
    assert (CPU_RECIPES["lift"].steps, CPU_RECIPES["lift"].optimizer_lr) == (3000, 6e-3)
    assert (CPU_RECIPES["can"].steps, CPU_RECIPES["can"].optimizer_lr) == (20_000, 3e-3)
    assert set(CPU_RECIPES) == set(CPU_TASKS) == {"lift", "can", "square"}


def test_layout_names_for_flags_and_generic_vectors():
    assert layout_names((("flag", 1), ("robot0_gripper_qpos", 2), ("x_quat", 4))) == [
        "flag", "robot0_gripper_qpos.0", "robot0_gripper_qpos.1", "x_quat.x", "x_quat.y", "x_quat.z", "x_quat.w"
    ]
