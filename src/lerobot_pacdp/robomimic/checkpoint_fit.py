"""Refuse to roll a checkpoint out in a robomimic task whose observations or actions it was not trained on.

lerobot-eval builds the environments before the policy and meets a mismatch (a Lift checkpoint with
`--env.task=can`) only inside the policy's normaliser, after a long traceback. A checkpoint says what
it takes: `config.json` holds its input and output feature shapes, `train_config.json` the dataset it
trained on, and that dataset's `meta/robomimic.json` (written by the converter) the task and the
robosuite generation. `RobomimicEnvConfig` runs this check while `--env.*` is parsed, so nothing starts.
"""

import json
from pathlib import Path
from typing import Any

from lerobot_pacdp.cli_errors import UserInputError
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.tasks import TASKS, RobomimicTask
from lerobot_pacdp.train_runs import PROCESSOR_FILES

CONVERTER_METADATA = ("meta", "robomimic.json")  # hdf5_adapter.METADATA_FILE, in the dataset's meta/


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return content if isinstance(content, dict) else None


def checkpoint_shapes(pretrained_dir: Path) -> dict[str, tuple[int, ...]] | None:
    """Feature key -> shape of a checkpoint's inputs and outputs (None if its config.json is unreadable)."""
    config = _read_json(pretrained_dir / "config.json")
    if config is None:
        return None
    features = {**(config.get("input_features") or {}), **(config.get("output_features") or {})}
    try:
        return {key: tuple(int(n) for n in feature["shape"]) for key, feature in features.items()}
    except (KeyError, TypeError, ValueError):
        return None


def training_dataset_metadata(pretrained_dir: Path) -> dict[str, Any] | None:
    """The converter's metadata of the dataset the checkpoint trained on, if that dataset is still on disk."""
    train_config = _read_json(pretrained_dir / "train_config.json")
    root = ((train_config or {}).get("dataset") or {}).get("root")
    return _read_json(Path(root).joinpath(*CONVERTER_METADATA)) if root else None


def _tasks_with_shapes(shapes: dict[str, tuple[int, ...]]) -> list[str]:
    return [name for name, task in TASKS.items() if _task_shapes(task) == shapes]


def _task_shapes(task: RobomimicTask) -> dict[str, tuple[int, ...]]:
    return {
        "observation.state": (task.state_dim,),
        "observation.environment_state": (task.object_dim,),
        "action": (task.action_dim,),
    }


def check_checkpoint_fits_env(
    pretrained_dir: Path, env_shapes: dict[str, tuple[int, ...]], task: str, robosuite_compat: str, compat_given: bool
) -> None:
    """Raise a `UserInputError` naming each mismatch and the task the checkpoint was trained on.

    `env_shapes` are the env's features under the policy's keys. A robosuite generation different from
    the one the training data was recorded with is refused too (same shapes, permuted values), unless
    `--env.robosuite_compat` was given explicitly, and so is a checkpoint without its processor files (a
    hub-style copy of `model.safetensors` and `config.json` only). A checkpoint whose config cannot be
    read is left to LeRobot.
    """
    shapes = checkpoint_shapes(pretrained_dir)
    if shapes is None:
        return
    meta = training_dataset_metadata(pretrained_dir) or {}
    if meta.get("task"):
        trained_on = f"{meta['task']} (meta/robomimic.json of its dataset)"
        fix_task = meta["task"]
    else:
        candidates = _tasks_with_shapes(shapes)
        trained_on = f"{' or '.join(candidates)} (by its feature shapes)" if candidates else "another dataset"
        fix_task = candidates[0] if len(candidates) == 1 else None

    mismatches = []
    for key, shape in shapes.items():
        provided = env_shapes.get(key)
        if provided is None:
            mismatches.append(f"it takes {key}, which the robomimic env does not provide")
        elif provided != shape:
            mismatches.append(f"{key} has shape {list(shape)} in the checkpoint but {list(provided)} in {task}")
    if mismatches:
        fix = f"evaluate it with --env.task={fix_task}" if fix_task else "evaluate it in the task it was trained on"
        raise UserInputError(
            f"the checkpoint {pretrained_dir} does not fit --env.task={task}: {'; '.join(mismatches)}. It was "
            f"trained on {trained_on}; {fix}."
        )

    missing = [name for name in PROCESSOR_FILES if not (pretrained_dir / name).is_file()]
    if missing:
        raise UserInputError(
            f"the checkpoint {pretrained_dir} lacks {' and '.join(missing)}, the processors (with the "
            "normalisation stats) lerobot-eval needs: copy them from the lerobot-train checkpoint it came from "
            "(checkpoints/<step>/pretrained_model/)."
        )

    recorded = meta.get("robosuite_compat")
    if recorded and not compat_given and compat.normalize_generation(recorded) != robosuite_compat:
        raise UserInputError(
            f"the checkpoint {pretrained_dir} was trained on {meta.get('task', task)} data recorded with robosuite "
            f"{recorded} conventions, but the env defaults to {robosuite_compat}: pass "
            f"--env.robosuite_compat={recorded} (or --env.robosuite_compat={robosuite_compat} to override)."
        )
