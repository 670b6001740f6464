"""lerobot-train output directories: where the checkpoints are, which are complete, where a run resumes.

LeRobot 0.6.1 writes `<output_dir>/checkpoints/<step>/{pretrained_model,training_state}/` file by file
(`save_checkpoint`) and points the `checkpoints/last` symlink at a checkpoint only once it is written
(`update_last_checkpoint`). The study, the metrics and pacdp-recover-run all read runs through this module.
"""

import json
from pathlib import Path
from typing import Any

CHECKPOINTS_DIR = "checkpoints"
LAST_LINK = "last"
PRETRAINED_DIR = "pretrained_model"
TRAINING_STATE_DIR = "training_state"
TRAIN_CONFIG_FILE = "train_config.json"
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")


def _json_problem(path: Path) -> str | None:
    if not path.is_file():
        return "missing"
    try:
        json.loads(path.read_text())
    except (OSError, ValueError):
        return "not valid JSON (cut off mid-write?)"
    return None


def _read_json(path: Path) -> Any:
    return None if _json_problem(path) else json.loads(path.read_text())


def _safetensors_problem(path: Path) -> str | None:
    """None if the file is as long as its own header says (safetensors: 8-byte header size, JSON header, data)."""
    if not path.is_file():
        return "missing"
    try:
        with path.open("rb") as f:
            header_size = int.from_bytes(f.read(8), "little")
            header = json.loads(f.read(header_size))
        data_end = max((t["data_offsets"][1] for k, t in header.items() if k != "__metadata__"), default=0)
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
        return "unreadable (cut off mid-write?)"
    expected, size = 8 + header_size + data_end, path.stat().st_size
    return None if size == expected else f"truncated ({size} of {expected} bytes)"


def checkpoint_problem(step_dir: Path) -> str | None:
    """What keeps a numbered lerobot-train checkpoint from being resumed or evaluated (None: complete).

    Every file LeRobot's `save_checkpoint` writes is checked, in the order it writes them.
    """
    pretrained, state = step_dir / PRETRAINED_DIR, step_dir / TRAINING_STATE_DIR
    missing_dirs = [f"{d.name}/ is missing" for d in (pretrained, state) if not d.is_dir()]
    if missing_dirs:
        return "; ".join(missing_dirs)
    checks = [
        (pretrained / "config.json", _json_problem),
        (pretrained / "model.safetensors", _safetensors_problem),
        (pretrained / TRAIN_CONFIG_FILE, _json_problem),
    ]
    for name in PROCESSOR_FILES:
        checks.append((pretrained / name, _json_problem))
        processor = _read_json(pretrained / name)
        steps = processor.get("steps", []) if isinstance(processor, dict) else []
        state_files = [s["state_file"] for s in steps if isinstance(s, dict) and s.get("state_file")]
        checks += [(pretrained / state_file, _safetensors_problem) for state_file in state_files]
    checks += [
        (state / "training_step.json", _json_problem),
        (state / "rng_state.safetensors", _safetensors_problem),
        (state / "optimizer_param_groups.json", _json_problem),
        (state / "optimizer_state.safetensors", _safetensors_problem),
    ]
    train_config = _read_json(pretrained / TRAIN_CONFIG_FILE)
    if isinstance(train_config, dict) and train_config.get("scheduler"):
        checks.append((state / "scheduler_state.json", _json_problem))
    problems = [f"{path.relative_to(step_dir)} is {problem}" for path, check in checks if (problem := check(path))]
    return "; ".join(problems) or None


def step_dirs(output_dir: Path) -> list[Path]:
    """The numbered checkpoint directories of a run, by step (complete or not; none if it has no checkpoints/)."""
    checkpoints = Path(output_dir) / CHECKPOINTS_DIR
    if not checkpoints.is_dir():
        return []
    return sorted((d for d in checkpoints.iterdir() if d.name.isdigit() and d.is_dir()), key=lambda d: int(d.name))


def checkpoint_step(step_dir: Path) -> int:
    """The training step of a numbered checkpoint (LeRobot names the directory by it)."""
    return int(Path(step_dir).name)


def last_checkpoint(output_dir: Path) -> Path | None:
    """The checkpoint `checkpoints/last` points at, if it is complete (where `--resume=true` continues)."""
    last = Path(output_dir) / CHECKPOINTS_DIR / LAST_LINK
    if not last.is_symlink():
        return None
    target = last.resolve()
    return target if target.name.isdigit() and checkpoint_problem(target) is None else None


def final_checkpoint(output_dir: Path, steps: int) -> Path | None:
    """The run's complete checkpoint at step `steps` (its last, for a run of `steps` steps), if written."""
    for step_dir in step_dirs(output_dir):
        if checkpoint_step(step_dir) == steps and checkpoint_problem(step_dir) is None:
            return step_dir
    return None


def resume_arguments(output_dir: Path) -> list[str]:
    """lerobot-train's arguments that continue the run from `checkpoints/last`."""
    config = Path(output_dir) / CHECKPOINTS_DIR / LAST_LINK / PRETRAINED_DIR / TRAIN_CONFIG_FILE
    return [f"--config_path={config}", "--resume=true"]
