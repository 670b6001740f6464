"""A gymnasium environment for the robomimic tasks, on robosuite 1.5 (imported here, so import lazily).

Observations come in the converter's layout under the raw keys LeRobot's `preprocess_observation` maps:
`agent_pos` -> `observation.state` (robot proprioception) and `environment_state` ->
`observation.environment_state` (robosuite's `object` vector). Actions are robomimic's delta OSC_POSE
commands in [-1, 1] (7 per arm). `info["is_success"]` is `env._check_success()`; success terminates
the episode and the task's budget (400 / 700 steps) truncates it.

`robosuite_compat="1.4"` makes a rollout look like the robosuite <= 1.4 recordings of the released
robomimic files (see `compat.py`): legacy `object` layout, world-frame OSC deltas, full physics.
"""

import contextlib
import logging
import warnings
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.rendering import choose_mujoco_gl
from lerobot_pacdp.robomimic.tasks import FPS, RobomimicTask, get_task

logger = logging.getLogger(__name__)

DEFAULT_RENDER_CAMERA = "agentview"
_NOISY_ROBOSUITE_MESSAGES = (
    "private macro file",
    "setup_macros.py",
    "robosuite_models",
    "mink-based whole-body IK",
    "Loading controller configuration",
    "but the robot does not have this component",
)


class _RobosuiteNoiseFilter(logging.Filter):
    """Drop robosuite's import/creation chatter (macro-file hints, optional packages, unused parts)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.ERROR:
            return True
        message = record.getMessage()
        return not any(noise in message for noise in _NOISY_ROBOSUITE_MESSAGES)


def _import_robosuite():
    """Import robosuite with its import-time chatter filtered out and an offscreen renderer chosen."""
    choose_mujoco_gl()
    robosuite_logger = logging.getLogger("robosuite_logs")
    if not any(isinstance(f, _RobosuiteNoiseFilter) for f in robosuite_logger.filters):
        robosuite_logger.addFilter(_RobosuiteNoiseFilter())
    try:
        import robosuite
    except ImportError as exc:  # pragma: no cover - robosuite is a dependency
        raise ImportError(
            "The robomimic environments need robosuite 1.5.1 with mujoco>=3.3,<3.10: "
            "pip install 'robosuite==1.5.1' 'mujoco>=3.3,<3.10'."
        ) from exc
    return robosuite


def controller_config(task: RobomimicTask, generation: str = compat.NATIVE) -> dict:
    """robosuite 1.5's BASIC composite controller (OSC_POSE deltas, robomimic's gains) for one Panda arm.

    Only the `right` arm part is kept (a Panda has nothing else), so robosuite does not warn about the
    unused parts; with the legacy generation, deltas are read in the world frame.
    """
    _import_robosuite()
    from robosuite.controllers import load_composite_controller_config

    config = load_composite_controller_config(controller="BASIC")
    # load_composite_controller_config flattens the file's `body_parts.arms.right` to `body_parts.right`.
    arm = dict(config["body_parts"]["right"])
    arm["input_ref_frame"] = compat.controller_input_ref_frame(generation)
    config["body_parts"] = {"right": arm}
    return config


def robosuite_kwargs(
    task: RobomimicTask | str,
    generation: str = compat.NATIVE,
    *,
    hard_reset: bool = True,
    lite_physics: bool | None = None,
) -> dict[str, Any]:
    """`robosuite.make`'s keyword arguments for a task with robomimic's settings (20 Hz, sparse reward,
    no cameras, object observations on). `lite_physics` defaults to False for the legacy generation, as
    robosuite advises for datasets collected with robosuite <= 1.4.1, and to robosuite's default otherwise."""
    task = get_task(task) if isinstance(task, str) else task
    generation = compat.normalize_generation(generation)
    kwargs: dict[str, Any] = {
        "robots": list(task.robots),
        "controller_configs": controller_config(task, generation),
        "has_renderer": False,
        "has_offscreen_renderer": False,
        "use_camera_obs": False,
        "use_object_obs": True,
        "reward_shaping": False,
        "control_freq": FPS,
        "ignore_done": True,
        "hard_reset": hard_reset,
    }
    if task.env_configuration is not None:
        kwargs["env_configuration"] = task.env_configuration
    if lite_physics is None and generation == compat.LEGACY:
        lite_physics = False
    if lite_physics is not None:
        kwargs["lite_physics"] = lite_physics
    return kwargs


def make_robosuite_env(
    task: RobomimicTask | str,
    generation: str = compat.NATIVE,
    *,
    hard_reset: bool = True,
    lite_physics: bool | None = None,
):
    """Create the raw robosuite environment of a task (settings: `robosuite_kwargs`)."""
    task = get_task(task) if isinstance(task, str) else task
    kwargs = robosuite_kwargs(task, generation, hard_reset=hard_reset, lite_physics=lite_physics)
    return _import_robosuite().make(task.env_name, **kwargs)


@contextlib.contextmanager
def seeded_reset_rngs(env, seed: int) -> Iterator[None]:
    """Make the next `env.reset()` deterministic for `seed`, whichever robosuite 1.5.x is installed.

    robosuite 1.5.1 samples object placements and joint noise from numpy's global generator; later
    releases from `env.rng` and the placement samplers' `rng`. Both are seeded; the global generator's
    state is restored afterwards so the caller's randomness is untouched.
    """
    seed = int(seed) % (2**32)
    env.rng = np.random.default_rng(seed)
    initializer = getattr(env, "placement_initializer", None)
    if initializer is not None:
        if hasattr(initializer, "rng"):
            initializer.rng = env.rng
        for sampler in getattr(initializer, "samplers", {}).values():
            if hasattr(sampler, "rng"):
                sampler.rng = env.rng
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)


def current_observations(env) -> dict[str, np.ndarray]:
    """The observations of the simulator's current state (difference 4).

    robosuite 1.5 computes `*_to_robot0_eef_*` before the object poses they read from the observation
    cache, so one forced pass after a reset or a state restore pairs them with the previous pass's poses
    (after `set_state`, another episode's can); a second pass reads the fresh ones.
    """
    env._get_observations(force_update=True)
    return env._get_observations(force_update=True)


def robosuite_reset(env, seed: int) -> dict[str, np.ndarray]:
    """Reset deterministically and return correct observations."""
    with seeded_reset_rngs(env, seed):
        env.reset()
    return current_observations(env)


def observation_vectors(
    task: RobomimicTask, raw_obs: dict[str, Any], generation: str = compat.NATIVE
) -> tuple[np.ndarray, np.ndarray]:
    """(proprioception, object) vectors in the converter's layout from a robosuite observation dict."""
    try:
        state = np.concatenate([np.atleast_1d(raw_obs[key]) for key in task.proprio_keys])
        obj = np.concatenate([np.atleast_1d(raw_obs[key]) for key, _ in task.object_layout])
    except KeyError as exc:
        raise KeyError(f"{task.name}: robosuite observation lacks {exc}; is robosuite 1.5 installed?") from None
    obj = obj.astype(np.float64)
    if compat.normalize_generation(generation) == compat.LEGACY:
        obj = compat.object_to_legacy(task, obj)
    return state.astype(np.float64), obj


class RobomimicEnv(gym.Env):
    """One robomimic task as a gymnasium environment (see the module docstring).

    Args:
        task: lift, can, square, transport or tool_hang.
        robosuite_compat: "1.5" (native layout; datasets recorded with robosuite 1.5, e.g. the scripted
            demos) or "1.4" (the released robomimic files, recorded with robosuite <= 1.4).
        episode_length: step budget; defaults to the task's (400 or 700).
        render_mode: "rgb_array" (frames from `render_camera`) or None.
        hard_reset: reload the MuJoCo model on every reset (robomimic's setting).
        lite_physics: robosuite's flag; None picks False for compat "1.4", robosuite's default otherwise.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        task: str = "lift",
        robosuite_compat: str = compat.NATIVE,
        episode_length: int | None = None,
        render_mode: str | None = "rgb_array",
        render_camera: str = DEFAULT_RENDER_CAMERA,
        render_height: int = 256,
        render_width: int = 256,
        hard_reset: bool = True,
        lite_physics: bool | None = None,
    ):
        super().__init__()
        self.robomimic_task = get_task(task)
        self.generation = compat.normalize_generation(robosuite_compat)
        self.episode_length = int(episode_length or self.robomimic_task.episode_length)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")
        self.render_mode = render_mode
        self.render_camera = render_camera
        self.render_height = int(render_height)
        self.render_width = int(render_width)
        # LeRobot's rollout reads these two (language-conditioned policies use them).
        self.task = self.robomimic_task.name
        self.task_description = self.robomimic_task.description

        self._env = make_robosuite_env(
            self.robomimic_task, self.generation, hard_reset=hard_reset, lite_physics=lite_physics
        )
        task_ = self.robomimic_task
        self.observation_space = gym.spaces.Dict(
            {
                "agent_pos": gym.spaces.Box(-np.inf, np.inf, shape=(task_.state_dim,), dtype=np.float64),
                "environment_state": gym.spaces.Box(-np.inf, np.inf, shape=(task_.object_dim,), dtype=np.float64),
            }
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(task_.action_dim,), dtype=np.float32)
        self._elapsed = 0
        self.last_raw_obs: dict[str, Any] = {}
        self._renderer = None
        self._renderer_model = None
        self._render_unavailable: str | None = None

    # ----------------------------------------------------------------------------------------------------
    @property
    def robosuite_env(self):
        """The wrapped robosuite environment (privileged state for scripted experts and tests)."""
        return self._env

    def _observation(self, raw_obs: dict[str, Any]) -> dict[str, np.ndarray]:
        self.last_raw_obs = raw_obs
        state, obj = observation_vectors(self.robomimic_task, raw_obs, self.generation)
        return {"agent_pos": state, "environment_state": obj}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset; the same `seed` always gives the same initial state. `options={"state": s}` then restores
        a flattened MuJoCo state `s` (a robomimic file's `states[t]`)."""
        super().reset(seed=seed)
        reset_seed = int(self.np_random.integers(0, 2**32 - 1))
        raw_obs = robosuite_reset(self._env, reset_seed)
        self._elapsed = 0
        if options and options.get("state") is not None:
            raw_obs = self.set_state(options["state"])
        return self._observation(raw_obs), {"is_success": bool(self._env._check_success())}

    def set_state(self, state: np.ndarray) -> dict[str, Any]:
        """Restore a flattened MuJoCo state ([time, qpos, qvel]) and return the raw robosuite observation."""
        self._env.sim.set_state_from_flattened(np.asarray(state, dtype=np.float64))
        self._env.sim.forward()
        return current_observations(self._env)

    def get_state(self) -> np.ndarray:
        """The flattened MuJoCo state, as robomimic files store it in `states`."""
        return np.array(self._env.sim.get_state().flatten())

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        if action.shape != (self.robomimic_task.action_dim,):
            task = self.robomimic_task
            raise ValueError(f"{task.name} takes {task.action_dim}-d actions, got shape {action.shape}.")
        raw_obs, reward, _, _ = self._env.step(action)
        self._elapsed += 1
        success = bool(self._env._check_success())
        truncated = self._elapsed >= self.episode_length and not success
        return self._observation(raw_obs), float(reward), success, truncated, {"is_success": success}

    # ----------------------------------------------------------------------------------------------------
    def render(self):
        """An RGB frame (H, W, 3) uint8 from `render_camera`.

        Needs an offscreen OpenGL context (MUJOCO_GL=egl or osmesa). Where none can be created, logs
        why once and returns black frames, so LeRobot's evaluation (which always records a few
        videos) carries on.
        """
        if self.render_mode is None:
            return None
        if self._render_unavailable is None:
            try:
                with warnings.catch_warnings():  # GLFW warns before failing where there is no display
                    warnings.simplefilter("ignore")
                    return self._render_frame()
            except Exception as exc:  # no GL context, missing library, ...
                self._render_unavailable = f"{type(exc).__name__}: {exc}"
                logger.warning(
                    "robomimic %s: offscreen rendering is unavailable (%s); videos will be blank. "
                    "Set MUJOCO_GL=egl (GPU) or MUJOCO_GL=osmesa (CPU, needs libOSMesa) to record videos.",
                    self.robomimic_task.name,
                    self._render_unavailable,
                )
        return np.zeros((self.render_height, self.render_width, 3), dtype=np.uint8)

    def _render_frame(self) -> np.ndarray:
        import mujoco

        model, data = self._env.sim.model._model, self._env.sim.data._data
        if self._renderer is None or self._renderer_model is not model:  # hard resets rebuild the model
            self._close_renderer()
            model.vis.quality.offsamples = 0  # no multisampling: a software renderer's frame costs ~1/3 less
            self._renderer = mujoco.Renderer(model, height=self.render_height, width=self.render_width)
            self._renderer_model = model
        self._renderer.update_scene(data, camera=self.render_camera)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False  # the floor's mirror pass, ~half a frame
        return np.array(self._renderer.render(), dtype=np.uint8)

    def _close_renderer(self) -> None:
        if self._renderer is not None:
            with contextlib.suppress(Exception):
                self._renderer.close()
        self._renderer = None
        self._renderer_model = None

    def close(self):
        self._close_renderer()
        env, self._env = getattr(self, "_env", None), None
        if env is not None:
            with contextlib.suppress(Exception):
                env.close()
