"""`pacdp-recover-run`: make a lerobot-train run that was killed while writing a checkpoint resumable again.

LeRobot writes `checkpoints/<step>/` file by file and points `checkpoints/last` at it only at the end,
so a run killed mid-write holds a numbered checkpoint without its processors or training state, and
either no `last` (killed during the first checkpoint) or a `last` that is fine but hidden behind a
broken newer directory. This finds the newest complete checkpoint (every file LeRobot writes present,
JSON parsable, safetensors not truncated), points `last` at it, and moves the incomplete ones to
`<output_dir>/incomplete_checkpoints/` (nothing is deleted), so that the README's resume command works.

    pacdp-recover-run --output_dir=outputs/pusht_pacdp
"""

import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli

CHECKPOINTS_DIR = "checkpoints"
LAST_LINK = "last"
PRETRAINED_DIR = "pretrained_model"
TRAINING_STATE_DIR = "training_state"
INCOMPLETE_DIR = "incomplete_checkpoints"
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
# An incomplete checkpoint touched more recently than this may belong to a run that is still saving it.
RECENT_WRITE_S = 60


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
        (pretrained / "train_config.json", _json_problem),
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
    train_config = _read_json(pretrained / "train_config.json")
    if isinstance(train_config, dict) and train_config.get("scheduler"):
        checks.append((state / "scheduler_state.json", _json_problem))
    problems = [f"{path.relative_to(step_dir)} is {problem}" for path, check in checks if (problem := check(path))]
    return "; ".join(problems) or None


@dataclass(frozen=True)
class Recovery:
    """What `recover_run` found and did."""

    checkpoint: Path  # the newest complete checkpoint, which `last` now points to
    step: int
    repointed: bool  # False if `last` already pointed at it
    set_aside: tuple[tuple[Path, str], ...]  # (new location, problem) of each incomplete checkpoint moved


def _step_dirs(checkpoints: Path) -> list[Path]:
    return sorted((d for d in checkpoints.iterdir() if d.name.isdigit() and d.is_dir()), key=lambda d: int(d.name))


def recover_run(output_dir: str | Path) -> Recovery:
    """Point `checkpoints/last` at the newest complete checkpoint and move incomplete ones aside."""
    output_dir = Path(output_dir).expanduser()
    checkpoints = output_dir / CHECKPOINTS_DIR
    if not checkpoints.is_dir():
        raise UserInputError(
            f"{output_dir} holds no {CHECKPOINTS_DIR}/ directory: either it is not a lerobot-train --output_dir, "
            f"or the run died before its first checkpoint and there is nothing to resume (remove {output_dir} "
            "and start the run again)."
        )
    found = [(d, checkpoint_problem(d)) for d in _step_dirs(checkpoints)]
    complete = [d for d, problem in found if problem is None]
    if not complete:
        details = "; ".join(f"{d.name}: {problem}" for d, problem in found) or "there are none"
        raise UserInputError(
            f"no complete checkpoint in {checkpoints} ({details}), so there is nothing to resume: remove "
            f"{output_dir} (or pass another --output_dir) and start the run again."
        )
    for step_dir, problem in found:
        age = time.time() - max((p.stat().st_mtime for p in step_dir.rglob("*")), default=step_dir.stat().st_mtime)
        if problem is not None and age < RECENT_WRITE_S:
            raise UserInputError(
                f"{step_dir} was written {age:.0f} s ago: the run may still be saving it. Stop lerobot-train (or "
                f"wait {RECENT_WRITE_S} s after it died) and run pacdp-recover-run again."
            )
    newest = complete[-1]
    last = checkpoints / LAST_LINK
    if last.exists() and not last.is_symlink():
        raise UserInputError(f"{last} is a real directory, not lerobot-train's link; move it away and run again.")
    repointed = not last.is_symlink() or os.readlink(last) != newest.name
    if repointed:
        staged = checkpoints / f".{LAST_LINK}.pid{os.getpid()}.partial"
        staged.unlink(missing_ok=True)
        staged.symlink_to(newest.name)
        os.replace(staged, last)
    set_aside = []
    for step_dir, problem in found:
        if problem is not None:
            target = output_dir / INCOMPLETE_DIR / step_dir.name
            suffix = 1
            while target.exists():
                target, suffix = output_dir / INCOMPLETE_DIR / f"{step_dir.name}.{suffix}", suffix + 1
            target.parent.mkdir(exist_ok=True)
            step_dir.rename(target)
            set_aside.append((target, problem))
    step = json.loads((newest / TRAINING_STATE_DIR / "training_step.json").read_text())["step"]
    return Recovery(newest, int(step), repointed, tuple(set_aside))


def resume_command(output_dir: Path) -> str:
    config = output_dir / CHECKPOINTS_DIR / LAST_LINK / PRETRAINED_DIR / "train_config.json"
    return f"lerobot-train --config_path={config} --resume=true"


@dataclass
class RecoverRunConfig:
    output_dir: Path | None = None  # the --output_dir of the lerobot-train run to recover


def _recover_and_report(cfg: RecoverRunConfig) -> int:
    if cfg.output_dir is None:
        raise UserInputError("pass --output_dir=DIR, the --output_dir of the lerobot-train run to recover.")
    recovery = recover_run(cfg.output_dir)
    name = recovery.checkpoint.name
    if recovery.repointed:
        print(f"Using checkpoint {name} (step {recovery.step}), the newest complete one: checkpoints/last now "
              "points to it.")
    else:
        print(f"Using checkpoint {name} (step {recovery.step}): checkpoints/last already pointed to it.")
    for target, problem in recovery.set_aside:
        print(f"Moved the incomplete checkpoint {target.name} to {target} ({problem}).")
    print(f"Resume with:\n  {resume_command(Path(cfg.output_dir).expanduser().absolute())}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`pacdp-recover-run`: one line and exit 2 when there is nothing to recover."""
    return run_draccus_cli("pacdp-recover-run", RecoverRunConfig, _recover_and_report, argv)


if __name__ == "__main__":
    sys.exit(main())
