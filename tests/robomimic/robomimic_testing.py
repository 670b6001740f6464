"""Helpers for the robomimic tests: hand-built files with the released robomimic files' (robosuite <= 1.4)
layout."""

import numpy as np

from lerobot_pacdp.robomimic.hdf5_format import Demo, write_robomimic_hdf5
from lerobot_pacdp.robomimic.tasks import RobomimicTask

# robomimic v0.1-era controller config (robosuite <= 1.4: a flat OSC_POSE dict).
LEGACY_CONTROLLER = {
    "type": "OSC_POSE",
    "input_max": 1,
    "input_min": -1,
    "output_max": [0.05, 0.05, 0.05, 0.5, 0.5, 0.5],
    "output_min": [-0.05, -0.05, -0.05, -0.5, -0.5, -0.5],
    "kp": 150,
    "damping_ratio": 1,
    "impedance_mode": "fixed",
    "kp_limits": [0, 300],
    "damping_ratio_limits": [0, 10],
    "position_limits": None,
    "orientation_limits": None,
    "uncouple_pos_ori": True,
    "control_delta": True,
    "interpolation": None,
    "ramp_ratio": 0.2,
}


def legacy_env_args(task: RobomimicTask, env_version: str | None = None) -> dict:
    """env_args as the released robomimic files store them (env_version only in the v1.4 re-release)."""
    kwargs = {
        "has_renderer": False,
        "has_offscreen_renderer": False,
        "ignore_done": True,
        "use_object_obs": True,
        "use_camera_obs": False,
        "control_freq": 20,
        "controller_configs": LEGACY_CONTROLLER,
        "robots": list(task.robots),
        "camera_depths": False,
        "camera_heights": 84,
        "camera_widths": 84,
        "reward_shaping": False,
    }
    if task.env_configuration:
        kwargs["env_configuration"] = task.env_configuration
    args = {"env_name": task.env_name, "type": 1, "env_kwargs": kwargs}
    if env_version is not None:
        args["env_version"] = env_version
    return args


def legacy_demo(task: RobomimicTask, length: int, rng: np.random.Generator, object_dim: int | None = None) -> Demo:
    """A demo with the released files' low-dim keys (random values; success on the last step)."""
    obs = {"object": rng.normal(size=(length + 1, object_dim or task.object_dim))}
    for i in range(task.num_robots):
        obs[f"robot{i}_eef_pos"] = rng.normal(size=(length + 1, 3))
        obs[f"robot{i}_eef_quat"] = rng.normal(size=(length + 1, 4))
        obs[f"robot{i}_gripper_qpos"] = rng.normal(size=(length + 1, 2))
        obs[f"robot{i}_joint_pos"] = rng.normal(size=(length + 1, 7))
        obs[f"robot{i}_eef_vel_lin"] = rng.normal(size=(length + 1, 3))
    rewards = np.zeros(length)
    rewards[-1] = 1.0
    dones = np.zeros(length, dtype=np.int64)
    dones[-1] = 1
    return Demo(
        states=rng.normal(size=(length, 32)),
        actions=rng.uniform(-1, 1, size=(length, task.action_dim)),
        rewards=rewards,
        dones=dones,
        obs={k: v[:-1] for k, v in obs.items()},
        next_obs={k: v[1:] for k, v in obs.items()},
    )


def write_legacy_file(path, task: RobomimicTask, num_demos=3, length=4, env_version=None, masks=None, seed=0, **demo_kwargs):
    rng = np.random.default_rng(seed)
    demos = [legacy_demo(task, length + i, rng, **demo_kwargs) for i in range(num_demos)]
    if masks is None:
        names = [f"demo_{i}" for i in range(num_demos)]
        masks = {"train": names[:-1], "valid": names[-1:]}
    return write_robomimic_hdf5(path, demos, legacy_env_args(task, env_version), masks), demos
