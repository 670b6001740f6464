"""Scripted experts for Lift, Can and Square, and robomimic-format demo files made with them.

The experts read privileged object poses from the simulator and command robomimic's delta OSC_POSE
actions (`[dx, dy, dz, drx, dry, drz, gripper]` in [-1, 1]; 1 unit = 5 cm / 0.5 rad): a waypoint state
machine per task with a proportional controller in position and in gripper yaw. Optional Gaussian action
noise (on the arm dimensions) makes the demonstrations diverse; only successful episodes are written.

    pacdp-scripted-demos --task=lift --num_demos=10 --output=demos.hdf5 --seed=0 [--action_noise=0.05]

The output has the schema of the released robomimic `low_dim.hdf5` files (recorded with robosuite 1.5,
so convert it and evaluate with the native layout, `--env.robosuite_compat=1.5`, the default).

The same seed records the same demos on every x86-64 machine: the command records with OpenBLAS's Haswell
kernels whatever CPU it runs on (see `blas_pinned_environment`).
"""

import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli
from lerobot_pacdp.robomimic.hdf5_format import ENV_TYPE_ROBOSUITE, Demo, split_masks, write_robomimic_hdf5
from lerobot_pacdp.robomimic.tasks import RobomimicTask, get_task

POS_SCALE = 0.05  # metres per action unit (robomimic's OSC output_max)
ROT_SCALE = 0.5  # radians per action unit
OPEN, CLOSE = -1.0, 1.0


# ----------------------------------------------------------------------------------------------------------
# Geometry helpers
def _wrap(angle: float, period: float = 2 * math.pi) -> float:
    """Wrap an angle to [-period/2, period/2)."""
    return (angle + period / 2) % period - period / 2


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _axis_angle(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    angle = math.acos(cos)
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    norm = np.linalg.norm(axis)
    if norm < 1e-9:  # angle ~ pi: any consistent axis will do
        axis = np.sqrt(np.clip((np.diag(rotation) + 1.0) / 2.0, 0.0, None))
        norm = np.linalg.norm(axis)
    return axis / norm * angle


def _yaw_of_matrix(rotation: np.ndarray) -> float:
    return math.atan2(rotation[1, 0], rotation[0, 0])


class _Arm:
    """Privileged read-out of one Panda arm of a robosuite 1.5 environment."""

    def __init__(self, env, robot_index: int = 0):
        self.env = env
        robot = env.robots[robot_index]
        self.site_id = robot.eef_site_id[robot.arms[0]]
        prefix = robot.gripper[robot.arms[0]].naming_prefix
        self.finger_ids = [env.sim.model.body_name2id(f"{prefix}{side}finger") for side in ("left", "right")]

    @property
    def pos(self) -> np.ndarray:
        return np.array(self.env.sim.data.site_xpos[self.site_id])

    @property
    def mat(self) -> np.ndarray:
        return np.array(self.env.sim.data.site_xmat[self.site_id]).reshape(3, 3)

    @property
    def finger_yaw(self) -> float:
        """Direction (in the horizontal plane) along which the fingers close."""
        left, right = (np.array(self.env.sim.data.body_xpos[i]) for i in self.finger_ids)
        d = left - right
        return math.atan2(d[1], d[0])


def _body_pose(env, body_id: int) -> tuple[np.ndarray, np.ndarray]:
    pos = np.array(env.sim.data.body_xpos[body_id])
    mat = np.array(env.sim.data.body_xmat[body_id]).reshape(3, 3)
    return pos, mat


# ----------------------------------------------------------------------------------------------------------
# Experts
class ScriptedExpert:
    """Base class: a waypoint state machine commanding a position and a gripper yaw.

    Subclasses implement `plan()`, returning (target eef position, gripper turn about the vertical relative
    to the reset orientation (radians) or None for no turn, gripper command); phases advance when targets
    are reached (or their timers run out).
    """

    max_speed = 0.8  # action units per step (<= 4 cm per step)
    max_rot_speed = 0.6

    def __init__(self, env, rng: np.random.Generator | None = None, action_noise: float = 0.0):
        self.env = env  # the robosuite environment
        self.arm = _Arm(env)
        self.rng = rng if rng is not None else np.random.default_rng()
        self.action_noise = float(action_noise)
        self.reset()

    def reset(self) -> None:
        self.phase = 0
        self.phase_steps = 0
        self.down = self.arm.mat  # the reset orientation points the gripper down
        self.down_finger_yaw = self.arm.finger_yaw
        self.grasp_angle: float | None = None  # the gripper turn chosen for the grasp

    def advance(self) -> None:
        self.phase += 1
        self.phase_steps = 0

    def plan(self) -> tuple[np.ndarray, float | None, float]:
        raise NotImplementedError

    @property
    def turn(self) -> float:
        """The gripper's current turn about the vertical relative to the reset orientation."""
        return _wrap(_yaw_of_matrix(self.arm.mat) - _yaw_of_matrix(self.down))

    def grasp_turn(self, closing_yaw: float, symmetry: float = math.pi) -> float:
        """The smallest turn that makes the fingers close along `closing_yaw` (modulo `symmetry`)."""
        return _wrap(closing_yaw - self.down_finger_yaw, symmetry)

    def act(self) -> np.ndarray:
        target, turn, gripper = self.plan()
        self.phase_steps += 1
        action = np.zeros(7)
        action[:3] = np.clip((target - self.arm.pos) / POS_SCALE, -self.max_speed, self.max_speed)
        # Target orientation: the reset (pointing-down) orientation turned by `turn` about the vertical.
        goal = _rot_z(turn) @ self.down if turn is not None else self.down
        error = _axis_angle(goal @ self.arm.mat.T)
        action[3:6] = np.clip(error / ROT_SCALE, -self.max_rot_speed, self.max_rot_speed)
        if self.action_noise > 0:
            action[:6] += self.rng.normal(0.0, self.action_noise, size=6)
        action[6] = gripper
        return np.clip(action, -1.0, 1.0)

    def near(self, target: np.ndarray, tolerance: float) -> bool:
        return bool(np.linalg.norm(target - self.arm.pos) < tolerance)


class LiftExpert(ScriptedExpert):
    """Above the cube -> down -> close -> lift."""

    def reset(self) -> None:
        super().reset()
        self.cube_id = self.env.cube_body_id

    def plan(self):
        cube, cube_mat = _body_pose(self.env, self.cube_id)
        if self.grasp_angle is None:  # close across two opposite faces (the cube is symmetric by 90 deg)
            self.grasp_angle = self.grasp_turn(_yaw_of_matrix(cube_mat), math.pi / 2)
        above, at = cube + [0, 0, 0.08], cube + [0, 0, -0.003]
        if self.phase == 0:  # above the cube, open
            if self.near(above, 0.015) and self.phase_steps > 3:
                self.advance()
            return above, self.grasp_angle, OPEN
        if self.phase == 1:  # down
            if self.near(at, 0.008) or self.phase_steps > 40:
                self.advance()
            return at, self.grasp_angle, OPEN
        if self.phase == 2:  # close
            if self.phase_steps >= 6:
                self.advance()
            return at, self.grasp_angle, CLOSE
        lifted = np.array([self.arm.pos[0], self.arm.pos[1], cube[2] + 0.25])
        return lifted, self.grasp_angle, CLOSE  # up (until the env reports success)


class CanExpert(ScriptedExpert):
    """Above the can -> down -> close -> up -> over its target in bin 2 -> down -> open -> up."""

    def reset(self) -> None:
        super().reset()
        self.can_id = self.env.obj_body_id[self.env.objects[self.env.object_id].name]
        # The can's quadrant of bin 2 (PickPlace.not_in_bin); aim at its corner nearest the robot, which is
        # comfortably inside the quadrant and within the arm's reach.
        env, object_id = self.env, self.env.object_id
        x_low = env.bin2_pos[0] - (env.bin_size[0] / 2 if object_id in (0, 2) else 0.0)
        y_low = env.bin2_pos[1] - (env.bin_size[1] / 2 if object_id < 2 else 0.0)
        self.goal = np.array([x_low + 0.045, y_low + 0.055, env.bin2_pos[2]])
        self.carry_z = env.bin2_pos[2] + 0.2  # the can clears the bins' walls

    def plan(self):
        can, _ = _body_pose(self.env, self.can_id)
        turn = None  # a can is round: keep the reset orientation
        if self.phase == 0:  # above the can
            above = can + [0, 0, 0.1]
            if self.near(above, 0.015) and self.phase_steps > 3:
                self.advance()
            return above, turn, OPEN
        if self.phase == 1:  # down around the can
            at = can + [0, 0, 0.0]
            if self.near(at, 0.01) or self.phase_steps > 40:
                self.advance()
            return at, turn, OPEN
        if self.phase == 2:  # close
            if self.phase_steps >= 8:
                self.advance()
            return can, turn, CLOSE
        if self.phase == 3:  # up
            up = np.array([self.arm.pos[0], self.arm.pos[1], self.carry_z])
            if abs(self.arm.pos[2] - self.carry_z) < 0.02:
                self.advance()
            return up, turn, CLOSE
        # Carry: steer the can (not the hand) over the goal.
        offset = self.arm.pos - can
        over = np.array([self.goal[0], self.goal[1], self.carry_z]) + [offset[0], offset[1], 0]
        if self.phase == 4:
            if np.linalg.norm((over - self.arm.pos)[:2]) < 0.01:
                self.advance()
            return over, turn, CLOSE
        if self.phase == 5:  # lower into the bin
            low = over - [0, 0, 0.1]
            if self.near(low, 0.015) or self.phase_steps > 30:
                self.advance()
            return low, turn, CLOSE
        if self.phase == 6:  # release
            if self.phase_steps >= 6:
                self.advance()
            return self.arm.pos, turn, OPEN
        return np.array([self.arm.pos[0], self.arm.pos[1], self.carry_z]), turn, OPEN


class SquareExpert(ScriptedExpert):
    """Grasp the nut's handle -> up -> turn the nut square to the peg -> over the peg -> down -> open."""

    handle_offset = 0.054  # handle site, along the nut's x axis (square-nut.xml)

    def reset(self) -> None:
        super().reset()
        self.nut = self.env.nuts[self.env.nut_id]
        self.nut_id = self.env.obj_body_id[self.nut.name]
        self.peg = np.array(self.env.sim.data.body_xpos[self.env.peg1_body_id])
        self.carry_z = self.peg[2] + 0.22
        peg_geoms = np.flatnonzero(self.env.sim.model.geom_bodyid == self.env.peg1_body_id)
        self.peg_top = self.peg[2] + float(self.env.sim.model.geom_size[peg_geoms[0]][2])
        self.turn_to: float | None = None

    def plan(self):
        nut, nut_mat = _body_pose(self.env, self.nut_id)
        nut_yaw = _yaw_of_matrix(nut_mat)
        handle = nut + nut_mat @ [self.handle_offset, 0.0, 0.0]
        table_z = self.env.table_offset[2]
        if self.grasp_angle is None:  # fingers close across the handle (along the nut's y axis)
            self.grasp_angle = self.grasp_turn(nut_yaw + math.pi / 2)
        if self.phase == 0:  # above the handle
            above = handle + [0, 0, 0.08]
            if self.near(above, 0.012) and self.phase_steps > 3:
                self.advance()
            return above, self.grasp_angle, OPEN
        if self.phase == 1:  # down
            at = handle + [0, 0, -0.002]
            if self.near(at, 0.006) or self.phase_steps > 40:
                self.advance()
            return at, self.grasp_angle, OPEN
        if self.phase == 2:  # close
            if self.phase_steps >= 8:
                self.advance()
            return handle, self.grasp_angle, CLOSE
        if self.phase >= 3 and self.phase <= 5 and self.arm.pos[2] > table_z + 0.1 and nut[2] < table_z + 0.03:
            self.phase, self.phase_steps, self.grasp_angle, self.turn_to = 0, 0, None, None  # missed: try again
            return self.arm.pos + [0, 0, 0.02], None, OPEN
        if self.turn_to is None:
            # Square the nut to the (axis-aligned) peg, choosing the multiple of 90 deg that needs the
            # smallest total gripper turn (large wrist turns run into joint limits).
            options = [_wrap(k * math.pi / 2 - nut_yaw) for k in range(4)]
            delta = min(options, key=lambda d: abs(self.turn + d))
            self.turn_to = _wrap(nut_yaw + delta)
        # Closed loop on the nut's yaw: turn the gripper by the nut's remaining yaw error.
        yaw_error = _wrap(self.turn_to - nut_yaw)
        turn = self.turn + yaw_error
        if self.phase == 3:  # up, turning the nut
            up = np.array([self.arm.pos[0], self.arm.pos[1], self.carry_z])
            if (abs(self.arm.pos[2] - self.carry_z) < 0.02 and abs(yaw_error) < 0.05) or self.phase_steps > 60:
                self.advance()
            return up, turn, CLOSE
        # Steer the nut's centre (not the hand) over the peg.
        offset = self.arm.pos - nut
        over = np.array([self.peg[0], self.peg[1], self.carry_z]) + [offset[0], offset[1], 0]
        xy_error = np.linalg.norm((nut - self.peg)[:2])
        if self.phase == 4:
            if (xy_error < 0.0025 and abs(yaw_error) < 0.035) or self.phase_steps > 80:
                self.advance()
            return over, turn, CLOSE
        if self.phase == 5:  # lower onto the peg, pausing above its top while the nut is off-centre
            low = np.array([over[0], over[1], table_z + 0.045 + offset[2]])
            if nut[2] < self.peg_top + 0.03:  # slowly once close to the peg's top
                low[2] = max(low[2], self.arm.pos[2] - 0.008)
            if xy_error > 0.002 and nut[2] > self.peg_top + 0.015:
                low[2] = max(low[2], min(self.arm.pos[2], self.peg_top + 0.025 + offset[2]))
            if nut[2] < table_z + 0.045 or self.phase_steps > 60:
                self.advance()
            return low, turn, CLOSE
        if self.phase == 6:  # release
            if self.phase_steps >= 6:
                self.advance()
            return self.arm.pos, self.turn, OPEN
        return np.array([self.arm.pos[0], self.arm.pos[1], self.carry_z]), self.turn, OPEN


EXPERTS: dict[str, type[ScriptedExpert]] = {"lift": LiftExpert, "can": CanExpert, "square": SquareExpert}


# ----------------------------------------------------------------------------------------------------------
# Collection
@dataclass
class CollectionStats:
    task: str
    attempts: int = 0
    successes: int = 0
    success_lengths: list[int] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def success_rate(self) -> float:
        return self.successes / self.attempts if self.attempts else 0.0

    def as_dict(self) -> dict:
        lengths = self.success_lengths
        return {
            "task": self.task,
            "attempts": self.attempts,
            "successes": self.successes,
            "success_rate": self.success_rate,
            "mean_success_length": float(np.mean(lengths)) if lengths else None,
            "seconds": self.seconds,
            "seconds_per_attempt": self.seconds / self.attempts if self.attempts else None,
        }


def _raw_obs_record(task: RobomimicTask, raw_obs: dict, object_vector: np.ndarray) -> dict[str, np.ndarray]:
    """The observation keys a robomimic low-dim file holds: `object` plus every robot* array."""
    record = {"object": np.asarray(object_vector, dtype=np.float64)}
    for key, value in raw_obs.items():
        if key.startswith("robot") and not key.endswith("-state"):
            record[key] = np.asarray(value, dtype=np.float64)
    return record


def run_episode(env, expert: ScriptedExpert, seed: int | None = None, record: bool = True) -> tuple[bool, Demo | None]:
    """Roll the expert out once in a `RobomimicEnv` (native layout); returns (success, demo or None).

    Like robomimic's `dataset_states_to_obs.py`, the recorded observations are recomputed from the saved
    MuJoCo states (`obs[t]` is exactly what the environment observes after restoring `states[t]`;
    robosuite's step observations lag the state by one physics substep).
    """
    from lerobot_pacdp.robomimic.env import observation_vectors

    env.reset(seed=seed)
    expert.env = env.robosuite_env
    expert.arm = _Arm(env.robosuite_env)  # hard resets rebuild the simulation
    expert.reset()
    states, actions, rewards, dones = [], [], [], []
    success = False
    for _ in range(env.episode_length):
        if record:
            states.append(env.get_state())
        action = expert.act()
        _, reward, success, truncated, _ = env.step(action)
        actions.append(action)
        rewards.append(reward)
        dones.append(int(success))
        if success or truncated:
            break
    if not (success and record):
        return success, None
    task = env.robomimic_task
    observations = []
    for state in [*states, env.get_state()]:
        raw = env.set_state(state)
        observations.append(_raw_obs_record(task, raw, observation_vectors(task, raw)[1]))
    stacked = {key: np.stack([o[key] for o in observations]) for key in observations[0]}
    demo = Demo(
        states=np.stack(states),
        actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float64),
        dones=np.asarray(dones, dtype=np.int64),
        obs={key: value[:-1] for key, value in stacked.items()},
        next_obs={key: value[1:] for key, value in stacked.items()},
        model_file=env.robosuite_env.sim.model.get_xml(),
    )
    demo.dones[-1] = 1
    return True, demo


def env_args_for(task: RobomimicTask, env) -> dict:
    """robomimic's `env_args` for files recorded by `collect_demos` (robosuite 1.5 composite controller)."""
    import robosuite

    from lerobot_pacdp.robomimic.env import robosuite_kwargs

    env_kwargs = robosuite_kwargs(task, hard_reset=True)
    env_kwargs["controller_configs"] = env.robosuite_env.robots[0].composite_controller_config  # as recorded
    env_kwargs["lite_physics"] = bool(getattr(env.robosuite_env, "lite_physics", True))
    return {"env_name": task.env_name, "env_version": robosuite.__version__, "type": ENV_TYPE_ROBOSUITE,
            "env_kwargs": env_kwargs}  # fmt: skip


def _expert_task(task: str, num_demos: int, action_noise: float) -> RobomimicTask:
    """The task of a collection, once its inputs are checked (a one-line error for each bad one)."""
    robomimic_task = get_task(task)
    if robomimic_task.name not in EXPERTS:
        raise UserInputError(
            f"no scripted expert for {robomimic_task.name!r}; scripted experts exist for {', '.join(EXPERTS)} "
            "(Transport and ToolHang need the released human demos)."
        )
    if num_demos < 1:
        raise UserInputError(f"--num_demos must be >= 1, got {num_demos}.")
    if action_noise < 0:
        raise UserInputError(f"--action_noise must be >= 0, got {action_noise}.")
    return robomimic_task


def collect_demos(
    task: str,
    num_demos: int,
    seed: int = 0,
    action_noise: float = 0.0,
    max_attempts: int | None = None,
    progress: bool = False,
) -> tuple[list[Demo], CollectionStats, dict]:
    """Run the task's expert until `num_demos` successes (or `max_attempts`, default 3x); returns
    (successful demos, statistics, env_args). Deterministic for a given seed."""
    from tqdm import tqdm

    from lerobot_pacdp.robomimic.env import RobomimicEnv

    robomimic_task = _expert_task(task, num_demos, action_noise)
    max_attempts = max_attempts or 3 * num_demos
    env = RobomimicEnv(robomimic_task.name, render_mode=None)
    expert = EXPERTS[robomimic_task.name](env.robosuite_env, np.random.default_rng(seed), action_noise)
    stats = CollectionStats(robomimic_task.name)
    demos: list[Demo] = []
    start = time.perf_counter()
    bar = tqdm(total=num_demos, desc=f"Scripted {robomimic_task.name} demos", unit="demo", disable=not progress)
    try:
        while len(demos) < num_demos and stats.attempts < max_attempts:
            success, demo = run_episode(env, expert, seed=seed if stats.attempts == 0 else None)
            stats.attempts += 1
            if success:
                stats.successes += 1
                stats.success_lengths.append(len(demo))
                demos.append(demo)
                bar.update(1)
            bar.set_postfix(success_rate=f"{stats.success_rate:.0%}")
        env_args = env_args_for(robomimic_task, env)
    finally:
        bar.close()
        env.close()
    stats.seconds = time.perf_counter() - start
    return demos, stats, env_args


def measure_success_rate(task: str, episodes: int, seed: int = 0, action_noise: float = 0.0) -> CollectionStats:
    """Success rate of the expert over `episodes` seeded episodes (nothing recorded)."""
    from lerobot_pacdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv(task, render_mode=None)
    expert = EXPERTS[get_task(task).name](env.robosuite_env, np.random.default_rng(seed), action_noise)
    stats = CollectionStats(get_task(task).name)
    start = time.perf_counter()
    try:
        for i in range(episodes):
            success, _ = run_episode(env, expert, seed=seed if i == 0 else None, record=False)
            stats.attempts += 1
            if success:
                stats.successes += 1
                stats.success_lengths.append(env._elapsed)
    finally:
        env.close()
    stats.seconds = time.perf_counter() - start
    return stats


@dataclass
class ScriptedDemosConfig:
    """`pacdp-scripted-demos`: scripted Lift/Can/Square demonstrations as a robomimic-format hdf5 file
    (successful episodes only)."""

    task: str | None = None  # lift, can or square
    num_demos: int | None = None  # successful demos to write
    output: Path | None = None  # the hdf5 file to write
    seed: int = 0
    action_noise: float = 0.0  # std of Gaussian noise on the arm actions
    valid_fraction: float = 0.1  # share of the demos in mask/valid
    max_attempts: int | None = None  # give up after this many episodes (default: 3 x num_demos)
    overwrite: bool = False  # replace an existing output file


# OpenBLAS picks its kernels by CPU when numpy loads it (Haswell's on AVX2 machines, SkylakeX's on AVX-512 ones),
# and the controllers' closed loop turns their last-bit differences into other demos: one seed's 60 Can demos
# differed in length on two machines. Haswell's kernels run on every AVX2 + FMA CPU.
BLAS_CORETYPE = "Haswell"


def blas_pinned_environment() -> dict[str, str] | None:
    """The environment to record in so that every x86-64 machine records the same demos, or None where this
    process already runs OpenBLAS's `BLAS_CORETYPE` kernels (or the CPU cannot run them)."""
    if os.environ.get("OPENBLAS_CORETYPE") == BLAS_CORETYPE or platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as cpu
    except ImportError:  # another numpy layout: record with whatever OpenBLAS chose
        return None
    if not (cpu.get("AVX2") and cpu.get("FMA3")):
        return None
    return {**os.environ, "OPENBLAS_CORETYPE": BLAS_CORETYPE}


def record_scripted_demos(cfg: ScriptedDemosConfig) -> int:
    """Record `cfg.num_demos` successful expert episodes into `cfg.output` and print what was recorded. OpenBLAS
    reads its core type once, when numpy loads it, so a process without the pinned one records in a child."""
    if cfg.task is None or cfg.num_demos is None or cfg.output is None:
        raise UserInputError(f"pass --task=<{'|'.join(EXPERTS)}> --num_demos=N --output=FILE.hdf5.")
    task = _expert_task(cfg.task, cfg.num_demos, cfg.action_noise)
    if cfg.output.exists() and not cfg.overwrite:
        raise UserInputError(f"{cfg.output} already exists; choose another --output or pass --overwrite=true.")
    if not 0.0 <= cfg.valid_fraction < 1.0:
        raise UserInputError(f"--valid_fraction must be in [0, 1), got {cfg.valid_fraction}.")
    if (env := blas_pinned_environment()) is not None:
        flags = [f"--{f.name}={str(v).lower() if isinstance(v, bool) else v}"
                 for f in fields(cfg) if (v := getattr(cfg, f.name)) is not None]  # fmt: skip
        code = subprocess.run([sys.executable, "-m", __spec__.name, *flags], env=env).returncode
        if code != 0:
            raise UserInputError(f"recording with OpenBLAS's {BLAS_CORETYPE} kernels failed (exit {code}; see above).")
        return 0
    demos, stats, env_args = collect_demos(
        task.name, cfg.num_demos, cfg.seed, cfg.action_noise, cfg.max_attempts, progress=True
    )
    if not demos:
        raise UserInputError(f"the {task.name} expert succeeded in none of {stats.attempts} episodes; nothing written.")
    write_robomimic_hdf5(
        cfg.output, demos, env_args, split_masks(len(demos), cfg.valid_fraction, cfg.seed),
        data_attrs={
            "scripted_expert": json.dumps({**stats.as_dict(), "seed": cfg.seed, "action_noise": cfg.action_noise})
        },
    )  # fmt: skip
    summary = stats.as_dict()
    print(
        f"{task.name}: {stats.successes}/{stats.attempts} successful episodes ({stats.success_rate:.0%}), "
        f"mean length {summary['mean_success_length']:.0f} steps, {stats.seconds:.0f} s; "
        f"wrote {len(demos)} demos to {cfg.output}"
    )
    if len(demos) < cfg.num_demos:
        print(
            f"warning: only {len(demos)} of the {cfg.num_demos} requested demos (max attempts reached)",
            file=sys.stderr,
        )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`pacdp-scripted-demos`: exits 2 with a one-line message on bad input."""
    return run_draccus_cli("pacdp-scripted-demos", ScriptedDemosConfig, record_scripted_demos, argv)


if __name__ == "__main__":
    sys.exit(main())
