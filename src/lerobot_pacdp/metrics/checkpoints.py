"""Find and load the checkpoints the metrics evaluate: `pacdp` or LeRobot `diffusion` policies.

Both types share LeRobot's diffusion U-Net, scheduler and processors, which is all the metrics use;
a PAC-DP policy is evaluated at its posterior mean unless a caller draws weights explicitly.
"""

import json
from dataclasses import dataclass
from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot.processor import PolicyProcessorPipeline

import lerobot_pacdp  # noqa: F401  (registers the `pacdp` type before any config is parsed)
from lerobot_pacdp.cli_errors import UserInputError
from lerobot_pacdp.train_runs import CHECKPOINTS_DIR, PRETRAINED_DIR, checkpoint_step, step_dirs

SUPPORTED_POLICY_TYPES = ("pacdp", "diffusion")
REQUIRED_FILES = ("config.json", "model.safetensors")


class MetricsError(UserInputError):
    """A user-facing problem with the inputs of a metric; the CLIs print it and exit 2."""


class CheckpointNotFoundError(MetricsError):
    pass


class UnsupportedPolicyError(MetricsError):
    pass


class DatasetMismatchError(MetricsError):
    pass


class CorruptCheckpointError(MetricsError):
    pass


@dataclass
class LoadedPolicy:
    """A checkpoint ready for evaluation: the policy (eval mode) and its saved processors."""

    path: Path
    policy: DiffusionPolicy
    preprocessor: PolicyProcessorPipeline
    postprocessor: PolicyProcessorPipeline

    @property
    def policy_type(self) -> str:
        return self.policy.config.type


def resolve_pretrained_dir(path: str | Path) -> Path:
    """The `pretrained_model` directory of `path`: itself, `path/pretrained_model`, or a checkpoint step dir."""
    path = Path(path)
    for candidate in (path, path / PRETRAINED_DIR):
        if all((candidate / name).is_file() for name in REQUIRED_FILES):
            return candidate
    if not path.exists():
        raise CheckpointNotFoundError(
            f"checkpoint {path} does not exist. Pass a `.../checkpoints/<step>/pretrained_model` directory "
            "(or the `<step>` directory) written by lerobot-train or `policy.save_pretrained`."
        )
    raise CheckpointNotFoundError(
        f"{path} is not a policy checkpoint: it holds no {' and '.join(REQUIRED_FILES)} (nor does "
        f"{path / PRETRAINED_DIR}). Pass a `.../checkpoints/<step>/pretrained_model` directory."
    )


def checkpoint_policy_type(pretrained_dir: Path) -> str:
    """The `type` recorded in config.json, refused unless the metrics can evaluate it."""
    try:
        policy_type = json.loads((pretrained_dir / "config.json").read_text()).get("type")
    except (OSError, json.JSONDecodeError) as exc:
        raise CheckpointNotFoundError(f"cannot read {pretrained_dir / 'config.json'}: {exc}") from None
    if policy_type not in SUPPORTED_POLICY_TYPES:
        raise UnsupportedPolicyError(
            f"{pretrained_dir} holds a {policy_type!r} policy; the metrics need a noise-prediction U-Net "
            f"and support only {' and '.join(map(repr, SUPPORTED_POLICY_TYPES))} checkpoints."
        )
    return policy_type


def load_policy(path: str | Path, device: str | None = None) -> LoadedPolicy:
    """Load a `pacdp` or `diffusion` checkpoint and its saved preprocessor (normalisation stats)."""
    pretrained_dir = resolve_pretrained_dir(path)
    policy_type = checkpoint_policy_type(pretrained_dir)
    try:  # safetensors, draccus and the policies raise many types for a truncated or foreign file
        config = PreTrainedConfig.from_pretrained(pretrained_dir)
        if device is not None:
            config.device = device
        policy = get_policy_class(policy_type).from_pretrained(pretrained_dir, config=config)
    except Exception as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise CorruptCheckpointError(
            f"cannot load the checkpoint {pretrained_dir}: {reason}. Its files are truncated, corrupt or from "
            "another network (was the run killed while writing it?); evaluate another checkpoint."
        ) from None
    try:
        preprocessor, postprocessor = make_pre_post_processors(
            config,
            pretrained_path=str(pretrained_dir),
            preprocessor_overrides={"device_processor": {"device": config.device}},
        )
    except FileNotFoundError as exc:
        raise CheckpointNotFoundError(
            f"{pretrained_dir} has no saved preprocessor ({exc}); the metrics need the checkpoint's "
            "normalisation stats. Save it with `preprocessor.save_pretrained(dir)` as lerobot-train does."
        ) from None
    return LoadedPolicy(pretrained_dir, policy, preprocessor, postprocessor)


def list_checkpoints(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(step, pretrained_model dir) of every numbered checkpoint of a lerobot-train output dir, by step.

    A single checkpoint (`.../checkpoints/<step>[/pretrained_model]` or a `save_pretrained` directory)
    is a run of one checkpoint; its step is the `<step>` directory's number, else 0.
    """
    run_dir = Path(run_dir)
    checkpoints_dir = run_dir / CHECKPOINTS_DIR
    if not checkpoints_dir.is_dir():
        if run_dir.exists() and any((d / "config.json").is_file() for d in (run_dir, run_dir / PRETRAINED_DIR)):
            pretrained_dir = resolve_pretrained_dir(run_dir)
            step_name = pretrained_dir.parent.name if pretrained_dir.name == PRETRAINED_DIR else ""
            return [(int(step_name) if step_name.isdigit() else 0, pretrained_dir)]
        raise CheckpointNotFoundError(
            f"{run_dir} is neither a lerobot-train output directory ({checkpoints_dir} does not exist) "
            "nor a checkpoint (no config.json)."
        )
    found = [(checkpoint_step(d), d / PRETRAINED_DIR) for d in step_dirs(run_dir) if (d / PRETRAINED_DIR).is_dir()]
    if not found:
        raise CheckpointNotFoundError(f"{checkpoints_dir} holds no `<step>/{PRETRAINED_DIR}` checkpoint.")
    return found
