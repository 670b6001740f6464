"""Where each run of a study stands, read from its directory alone (so any process, on any node, can tell).

A run directory holds `train_request.json` (its lerobot-train config), `train.log` (every call's output),
`dataset.json` (the fingerprint of the demos it started on; none in runs started before they were kept),
`done.json` once its final checkpoint is written, `slurm_job.json` once it was submitted to SLURM, and
lerobot-train's output dir `train/`. A run is done when its final checkpoint is complete, resumable from
`checkpoints/last` when that is complete, and new otherwise (`lerobot_pacdp.train_runs` reads the checkpoints).
"""

import json
import time
from pathlib import Path
from typing import Literal, NamedTuple

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.study.plan import RunSpec
from lerobot_pacdp.study.presets import StudyError
from lerobot_pacdp.train_runs import checkpoint_step, final_checkpoint, last_checkpoint

REQUEST_FILE, DONE_FILE, LOG_FILE, JOB_FILE = "train_request.json", "done.json", "train.log", "slurm_job.json"
DATASET_FILE = "dataset.json"


class RunState(NamedTuple):
    status: Literal["done", "resume", "new"]
    step: int  # the last complete checkpoint's step (the run's steps when done, 0 when new)


def write_json_atomic(path: Path, content) -> None:
    """JSON through `write_text_atomic`: readers never see a half-written file."""
    write_text_atomic(path, json.dumps(content, indent=2) + "\n")


def run_state(spec: RunSpec, output_dir: Path) -> RunState:
    run_dir, train_dir = spec.run_dir(output_dir), spec.train_dir(output_dir)
    if (run_dir / DONE_FILE).is_file() or final_checkpoint(train_dir, spec.steps) is not None:
        return RunState("done", spec.steps)
    last = last_checkpoint(train_dir)
    return RunState("resume", checkpoint_step(last)) if last is not None else RunState("new", 0)


def mark_done(spec: RunSpec, output_dir: Path, seconds: float | None) -> None:
    final = final_checkpoint(spec.train_dir(output_dir), spec.steps)
    write_json_atomic(
        spec.run_dir(output_dir) / DONE_FILE,
        {"run": spec.name, "steps": spec.steps, "final_checkpoint": str(final), "last_call_seconds": seconds,
         "finished": time.strftime("%Y-%m-%d %H:%M:%S")},
    )  # fmt: skip


def check_requests(specs: list[RunSpec], output_dir: Path) -> None:
    """Refuse to continue a run dir that was started with other episodes or steps (a changed preset)."""
    for spec in specs:
        request = spec.run_dir(output_dir) / REQUEST_FILE
        if request.is_file():
            old = json.loads(request.read_text())
            if old["dataset"]["episodes"] != list(spec.train_episodes) or old["steps"] != spec.steps:
                raise StudyError(
                    f"{spec.run_dir(output_dir)} was started with other training episodes or steps than this "
                    "plan; use another --output_dir (or restore the settings it was started with)."
                )


def trained_on(spec: RunSpec, output_dir: Path) -> str | None:
    """The fingerprint of the demos the run started on (`data.dataset_fingerprint`); None: not kept."""
    path = spec.run_dir(output_dir) / DATASET_FILE
    return json.loads(path.read_text())["fingerprint"] if path.is_file() else None


def check_datasets(specs: list[RunSpec], output_dir: Path, fingerprints: dict[str, str | None],
                   record: bool) -> None:  # fmt: skip
    """Refuse runs that started on another recording of their task's demos than the one under `output_dir` now
    (`fingerprints`, by task; it was deleted and recorded again): training would go on, and their held-out
    metrics be computed, on other demos. With `record`, new runs keep the fingerprint they start on."""
    known = [(spec, trained_on(spec, output_dir), fingerprints.get(spec.task)) for spec in specs]
    for spec, started, current in known:
        if current is not None and started is not None and started != current:
            raise StudyError(
                f"{spec.run_dir(output_dir)} started on another recording of the {spec.task} demos than "
                f"the one in {output_dir} now (fingerprint {started}, now {current}); use another "
                "--output_dir, or restore the recording it started on."
            )
    for spec, started, current in known:  # once all are checked: nothing kept for a refused call
        if record and current is not None and started is None and run_state(spec, output_dir).status == "new":
            write_json_atomic(spec.run_dir(output_dir) / DATASET_FILE, {"fingerprint": current})


def submitted_job(spec: RunSpec, output_dir: Path) -> dict | None:
    """The SLURM job this run was last submitted as (`slurm_job.json`), if any."""
    path = spec.run_dir(output_dir) / JOB_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def format_plan(specs: list[RunSpec], output_dir: Path) -> str:
    """The plan (held-out and training demos per seed) and each run's state, as `--dry_run=true` prints it."""
    lines = []
    for task in dict.fromkeys(s.task for s in specs):
        lines.append(f"task {task}:")
        for seed in dict.fromkeys(s.seed for s in specs if s.task == task):
            runs = [s for s in specs if s.task == task and s.seed == seed]
            lines.append(f"  seed {seed}: held-out demos ({len(runs[0].heldout_episodes)}): {list(runs[0].heldout_episodes)}")
            for demos in dict.fromkeys(s.demos for s in runs):
                first = next(s for s in runs if s.demos == demos)
                lines.append(f"    {demos} training demos (same for every method): {list(first.train_episodes)}")
    lines.append(f"{'run':<42}{'method':<11}{'lambda':>9}{'rho':>7}{'steps':>9}  state")
    for spec in specs:
        status, step = run_state(spec, output_dir)
        state = {"done": "done (skipped)", "resume": f"resume from step {step}", "new": "new"}[status]
        job = submitted_job(spec, output_dir)
        if job is not None and status != "done":
            state += f" (submitted as SLURM job {job['job_id']})"
        kl = "" if spec.kl_weight is None else f"{spec.kl_weight:g}"
        rho = "" if spec.prior_rho is None else f"{spec.prior_rho:g}"
        lines.append(f"{spec.task + '/' + spec.name:<42}{spec.method:<11}{kl:>9}{rho:>7}{spec.steps:>9}  {state}")
    return "\n".join(lines)
