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

from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli
from lerobot_pacdp.train_runs import (
    CHECKPOINTS_DIR,
    LAST_LINK,
    TRAINING_STATE_DIR,
    checkpoint_problem,
    resume_arguments,
    step_dirs,
)

INCOMPLETE_DIR = "incomplete_checkpoints"
# An incomplete checkpoint touched more recently than this may belong to a run that is still saving it.
RECENT_WRITE_S = 60


@dataclass(frozen=True)
class Recovery:
    """What `recover_run` found and did."""

    checkpoint: Path  # the newest complete checkpoint, which `last` now points to
    step: int
    repointed: bool  # False if `last` already pointed at it
    set_aside: tuple[tuple[Path, str], ...]  # (new location, problem) of each incomplete checkpoint moved


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
    found = [(d, checkpoint_problem(d)) for d in step_dirs(output_dir)]
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
    return " ".join(["lerobot-train", *resume_arguments(output_dir)])


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
