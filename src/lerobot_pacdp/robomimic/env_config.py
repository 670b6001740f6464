"""`--env.type=robomimic`: the robomimic tasks as a LeRobot environment type.

Importing this module registers the env type with LeRobot and one gymnasium id per task
(`pacdp_robomimic/<task>-v0`) whose entry point is the string
`"lerobot_pacdp.robomimic.env:RobomimicEnv"`, so robosuite/mujoco are only imported when an environment
is actually built (every LeRobot script imports plugins, so this module stays light).

    lerobot-eval --policy.path=... --env.type=robomimic --env.task=square \
        [--env.robosuite_compat=1.4] --eval.n_episodes=50 --eval.batch_size=10

`features` / `features_map` follow LeRobot's PushT config: the env emits `agent_pos` (robot
proprioception, -> `observation.state`) and `environment_state` (the `object` vector,
-> `observation.environment_state`), and takes a 7-d (14-d for Transport) `action`.
"""

from dataclasses import dataclass, field
from pathlib import Path

from gymnasium.envs.registration import register, registry
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGE, OBS_STATE

from lerobot_pacdp.cli_errors import UserInputError
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.checkpoint_fit import check_checkpoint_fits_env
from lerobot_pacdp.robomimic.tasks import FPS, TASK_NAMES, TASKS, get_task

ENTRY_POINT = "lerobot_pacdp.robomimic.env:RobomimicEnv"
GYM_NAMESPACE = "pacdp_robomimic"


def gym_id(task: str) -> str:
    """The gymnasium id of a task, e.g. `pacdp_robomimic/lift-v0`."""
    return f"{GYM_NAMESPACE}/{get_task(task).name}-v0"


def register_gym_envs() -> None:
    """Register every task's gymnasium id (idempotent; imports nothing heavy)."""
    for name, task in TASKS.items():
        env_id = gym_id(name)
        if env_id not in registry:
            register(id=env_id, entry_point=ENTRY_POINT, kwargs={"task": name}, max_episode_steps=task.episode_length)


register_gym_envs()


@EnvConfig.register_subclass("robomimic")
@dataclass
class RobomimicEnvConfig(EnvConfig):
    """LeRobot env config for the robomimic tasks (state-based, robosuite 1.5).

    Attributes:
        task: lift | can | square | transport | tool_hang.
        robosuite_compat: "1.5" for policies trained on robosuite 1.5 data (e.g. the scripted demos),
            "1.4" for policies trained on the released robomimic files (recorded with robosuite <= 1.4).
            The converter records which one a dataset needs in `meta/robomimic.json`.
        episode_length: step budget; None uses the task's (400 for Lift/Can/Square, 700 otherwise).
        render_*: the frames LeRobot's evaluation records as videos (needs MUJOCO_GL=egl or osmesa;
            without an offscreen renderer the videos are blank and a warning says why).
    """

    task: str | None = "lift"
    fps: int = FPS
    robosuite_compat: str = compat.NATIVE
    episode_length: int | None = None
    render_mode: str = "rgb_array"
    render_camera: str = "agentview"
    observation_height: int = 256
    observation_width: int = 256
    hard_reset: bool = True
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
            "pixels": OBS_IMAGE,
        }
    )

    def __post_init__(self):
        try:
            robomimic_task = get_task(self.task if self.task is not None else "")
        except ValueError:
            raise UserInputError(
                f"--env.task={self.task!r} is not a robomimic task; choose one of {', '.join(TASK_NAMES)}."
            ) from None
        self.task = robomimic_task.name
        try:
            self.robosuite_compat = compat.normalize_generation(self.robosuite_compat)
        except ValueError as exc:
            raise UserInputError(f"--env.{exc}") from None
        if self.episode_length is None:
            self.episode_length = robomimic_task.episode_length
        if self.episode_length < 1:
            raise UserInputError(f"--env.episode_length must be >= 1, got {self.episode_length}.")
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(robomimic_task.action_dim,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(robomimic_task.state_dim,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(robomimic_task.object_dim,)),
        }
        self._check_policy_given_on_the_command_line()

    def _check_policy_given_on_the_command_line(self) -> None:
        """lerobot-eval builds this env before it loads `--policy.path`: check now that the checkpoint fits
        the task (read from the command line as LeRobot's own EvalPipelineConfig reads it)."""
        from lerobot.configs import parser

        policy_path = parser.get_path_arg("policy")
        if policy_path is None or not Path(policy_path).is_dir():
            return
        env_shapes = {self.features_map[key]: tuple(feature.shape) for key, feature in self.features.items()}
        compat_given = parser.parse_arg("env.robosuite_compat") is not None
        check_checkpoint_fits_env(Path(policy_path), env_shapes, self.task, self.robosuite_compat, compat_given)

    @property
    def package_name(self) -> str:
        # Imported by EnvConfig.create_envs if the gym id is missing; importing it registers the ids.
        return "lerobot_pacdp.robomimic.env_config"

    @property
    def gym_id(self) -> str:
        return gym_id(self.task)

    @property
    def gym_kwargs(self) -> dict:
        return {
            "robosuite_compat": self.robosuite_compat,
            "episode_length": self.episode_length,
            "render_mode": self.render_mode,
            "render_camera": self.render_camera,
            "render_height": self.observation_height,
            "render_width": self.observation_width,
            "hard_reset": self.hard_reset,
            "max_episode_steps": self.episode_length,
        }
