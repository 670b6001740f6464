"""The robomimic task table: the single source of truth for every robomimic fact this package uses.

Each task of the paper (Lift, Can, Square, Transport, ToolHang; state-based, proficient-human `ph` demos)
is described once here: the robosuite environment that runs it, the episode budget, the observation
layout (robot proprioception -> `observation.state`, robosuite's `object-state` vector ->
`observation.environment_state`), the action size, and the paper's PAC-DP settings (lambda, training
steps). The converter, the gym environment, the LeRobot env config, the scripted experts, the config files
in `configs/robomimic/` and the tests all read this table.

The object layout is robosuite 1.5's (what the environment emits natively); `compat.py` derives the
layout of files recorded with robosuite <= 1.4 from it. Importing this module is cheap (no robosuite).
"""

import math
from dataclasses import dataclass

from lerobot_pacdp.cli_errors import UserInputError

FPS = 20  # robomimic control frequency (Hz)
PAPER_NUM_DEMOS = 200  # `ph` demos per task
PAPER_EVAL_FRACTION = 0.3  # 140 training / 60 held-out demos
PAPER_HELDOUT_DEMOS = math.ceil(PAPER_NUM_DEMOS * PAPER_EVAL_FRACTION)  # as LeRobot's eval split counts them: 60
# The paper's low-data demo counts (Table II). Its "200" trains on the 140 left after holding 60 out.
LOW_DATA_DEMO_COUNTS = (20, 40, 80, 200)
LOW_DATA_TRAINING_DEMOS = tuple(min(n, PAPER_NUM_DEMOS - PAPER_HELDOUT_DEMOS) for n in LOW_DATA_DEMO_COUNTS)

# Per-robot proprioception that Diffusion Policy observes (robomimic key, size).
PROPRIO_KEYS: tuple[tuple[str, int], ...] = (("eef_pos", 3), ("eef_quat", 4), ("gripper_qpos", 2))
_AXES = {3: ("x", "y", "z"), 4: ("x", "y", "z", "w")}  # robosuite quaternions are (x, y, z, w)
ARM_ACTION_NAMES = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")


@dataclass(frozen=True)
class RobomimicTask:
    """One robomimic task.

    Attributes:
        name: the task's short name (`--env.task` value): lift, can, square, transport, tool_hang.
        env_name: robosuite environment class name (also `env_args["env_name"]` in robomimic files).
        robots: robosuite robot names, one per arm.
        env_configuration: robosuite `env_configuration` (two-arm tasks only).
        episode_length: rollout budget in control steps (Diffusion Policy / robomimic evaluation).
        object_layout: robosuite 1.5 `object-state` layout, as (observable key, size) in emission order.
        kl_weight: the paper's lambda for this task.
        train_steps: the paper's number of training steps.
        description: natural-language task string stored in datasets and returned by the env.
    """

    name: str
    env_name: str
    robots: tuple[str, ...]
    env_configuration: str | None
    episode_length: int
    object_layout: tuple[tuple[str, int], ...]
    kl_weight: float
    train_steps: int
    description: str

    @property
    def num_robots(self) -> int:
        return len(self.robots)

    @property
    def action_dim(self) -> int:
        return 7 * self.num_robots

    @property
    def proprio_keys(self) -> tuple[str, ...]:
        """robomimic observation keys concatenated (in this order) into `observation.state`."""
        return tuple(f"robot{i}_{key}" for i in range(self.num_robots) for key, _ in PROPRIO_KEYS)

    @property
    def proprio_layout(self) -> tuple[tuple[str, int], ...]:
        return tuple((f"robot{i}_{key}", size) for i in range(self.num_robots) for key, size in PROPRIO_KEYS)

    @property
    def state_dim(self) -> int:
        return sum(size for _, size in self.proprio_layout)

    @property
    def object_dim(self) -> int:
        return sum(size for _, size in self.object_layout)

    @property
    def obs_dim(self) -> int:
        """Diffusion Policy's total low-dim observation size (object + proprioception)."""
        return self.state_dim + self.object_dim

    @property
    def action_names(self) -> list[str]:
        if self.num_robots == 1:
            return list(ARM_ACTION_NAMES)
        return [f"robot{i}_{n}" for i in range(self.num_robots) for n in ARM_ACTION_NAMES]

    @property
    def state_names(self) -> list[str]:
        return layout_names(self.proprio_layout)

    @property
    def object_names(self) -> list[str]:
        return layout_names(self.object_layout)


def layout_names(layout: tuple[tuple[str, int], ...]) -> list[str]:
    """Per-dimension feature names for a layout, e.g. `cube_pos.x`, `cube_quat.w`, `robot0_gripper_qpos.0`."""
    names = []
    for key, size in layout:
        if size == 1:
            names.append(key)
        elif (size == 4 and "quat" in key) or (size == 3 and "qpos" not in key):
            names.extend(f"{key}.{axis}" for axis in _AXES[size])
        else:
            names.extend(f"{key}.{i}" for i in range(size))
    return names


def layout_slices(layout: tuple[tuple[str, int], ...]) -> dict[str, list[int]]:
    """`{key: [start, stop]}` of each observable inside the concatenated vector."""
    slices, start = {}, 0
    for key, size in layout:
        slices[key] = [start, start + size]
        start += size
    return slices


def _object(name: str) -> tuple[tuple[str, int], ...]:
    """robosuite 1.5's per-object block: pose relative to the end effector first, then the world pose."""
    return (
        (f"{name}_to_robot0_eef_pos", 3),
        (f"{name}_to_robot0_eef_quat", 4),
        (f"{name}_pos", 3),
        (f"{name}_quat", 4),
    )


TASKS: dict[str, RobomimicTask] = {
    task.name: task
    for task in (
        RobomimicTask(
            name="lift",
            env_name="Lift",
            robots=("Panda",),
            env_configuration=None,
            episode_length=400,
            object_layout=(("cube_pos", 3), ("cube_quat", 4), ("gripper_to_cube_pos", 3)),
            kl_weight=1e-5,
            train_steps=250_000,
            description="Lift the cube from the table.",
        ),
        RobomimicTask(
            name="can",
            env_name="PickPlaceCan",
            robots=("Panda",),
            env_configuration=None,
            episode_length=400,
            object_layout=_object("Can"),
            kl_weight=1e-5,
            train_steps=250_000,
            description="Pick up the can and place it in its bin.",
        ),
        RobomimicTask(
            name="square",
            env_name="NutAssemblySquare",
            robots=("Panda",),
            env_configuration=None,
            episode_length=400,
            object_layout=_object("SquareNut"),
            kl_weight=1e-6,
            train_steps=250_000,
            description="Pick up the square nut and fit it onto the square peg.",
        ),
        RobomimicTask(
            name="transport",
            env_name="TwoArmTransport",
            robots=("Panda", "Panda"),
            env_configuration="single-arm-opposed",
            episode_length=700,
            object_layout=(
                ("payload_pos", 3),
                ("payload_quat", 4),
                ("trash_pos", 3),
                ("trash_quat", 4),
                ("lid_handle_pos", 3),
                ("lid_handle_quat", 4),
                ("target_bin_pos", 3),
                ("trash_bin_pos", 3),
                ("payload_in_target_bin", 1),
                ("trash_in_trash_bin", 1),
                ("gripper0_to_payload", 3),
                ("gripper0_to_lid_handle", 3),
                ("gripper1_to_payload", 3),
                ("gripper1_to_trash", 3),
            ),
            kl_weight=1e-6,
            train_steps=500_000,
            description="Transport the payload to the target bin with two arms and throw the trash into the trash bin.",
        ),
        RobomimicTask(
            name="tool_hang",
            env_name="ToolHang",
            robots=("Panda",),
            env_configuration=None,
            episode_length=700,
            object_layout=_object("base") + _object("frame") + _object("tool")
            + (("frame_is_assembled", 1), ("tool_on_frame", 1)),
            kl_weight=1e-5,
            train_steps=500_000,
            description="Assemble the frame on its stand and hang the tool on the frame.",
        ),
    )
}

TASK_NAMES = tuple(TASKS)
_BY_ENV_NAME = {task.env_name: task for task in TASKS.values()}


def get_task(name: str) -> RobomimicTask:
    """Look a task up by its short name (`lift`) or robosuite name (`Lift`), with a helpful error."""
    key = str(name).strip()
    task = TASKS.get(key.lower().replace("-", "_")) or _BY_ENV_NAME.get(key)
    if task is None:
        raise UserInputError(f"unknown robomimic task {name!r}; choose one of {', '.join(TASK_NAMES)}.")
    return task


def task_for_env_name(env_name: str) -> RobomimicTask | None:
    """The task whose robosuite environment is `env_name` (as stored in a robomimic file), or None."""
    return _BY_ENV_NAME.get(env_name)
