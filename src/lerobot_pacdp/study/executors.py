"""Where a study's runs execute: each run is one lerobot-train call; this is the local pool (`--executor=local`).

A call trains a new run from its `train_request.json` or resumes an interrupted one from `checkpoints/last`
(`--resume=true`); a run that died before its first checkpoint starts again. The SLURM executor
(`lerobot_pacdp.study.slurm`) makes the same calls from a job array.
"""

import logging
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from lerobot_pacdp.study.plan import RunSpec
from lerobot_pacdp.study.presets import StudyError
from lerobot_pacdp.study.state import DONE_FILE, LOG_FILE, REQUEST_FILE, RunState, mark_done, run_state
from lerobot_pacdp.train_hooks import IN_MEMORY_DATA_ENV
from lerobot_pacdp.train_runs import checkpoint_step, final_checkpoint, last_checkpoint, resume_arguments

logger = logging.getLogger("pacdp-study")

POLL_S, HEARTBEAT_S = 2.0, 60.0
# A run stopped by one of these (a user or scheduler ending it, not a crash) is paused: rerunning resumes it.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
# Starts each lerobot-train call's part of a run's train.log (calls append: a resumed run's log holds them all).
CALL_HEADER = "\n===== "


@dataclass(frozen=True)
class Outcome:
    """What became of the runs an executor was given."""

    done: tuple[RunSpec, ...] = ()
    paused: tuple[RunSpec, ...] = ()  # stopped at a checkpoint (chunk limit, SIGTERM/SIGINT): rerun to continue
    failed: tuple[RunSpec, ...] = ()
    submitted: tuple[RunSpec, ...] = ()  # handed to a scheduler that runs them later (SLURM)


def default_trainer() -> list[str]:
    local = Path(sys.executable).parent / "lerobot-train"
    found = str(local) if local.exists() else shutil.which("lerobot-train")
    if found is None:
        raise StudyError("lerobot-train is not on PATH; install lerobot (pip install -e .) in this environment.")
    return [found]


def time_left(running: list[float], waiting: list[float], jobs: int) -> float:
    """Seconds until the last run ends: the running runs' remaining seconds occupy their slots, and each waiting
    run starts in the first slot to free up (the pool's order). One run cannot use two slots."""
    slots = sorted(running + [0.0] * max(0, jobs - len(running)))
    for seconds in waiting:
        slots[0] += seconds
        slots.sort()
    return max(slots, default=0.0)


def train_command(spec: RunSpec, output_dir: Path, trainer: list[str], state: RunState) -> list[str]:
    """The lerobot-train call that continues `spec` from `state` (a new run: its request file)."""
    if state.status == "resume":
        return [*trainer, *resume_arguments(spec.train_dir(output_dir))]
    return [*trainer, f"--config_path={spec.run_dir(output_dir) / REQUEST_FILE}"]


def clear_unstarted(spec: RunSpec, output_dir: Path, state: RunState) -> None:
    """A run that died before its first checkpoint has nothing to resume: lerobot-train needs its dir gone."""
    train_dir = spec.train_dir(output_dir)
    if state.status == "new" and train_dir.exists():
        logger.info("  %s: removing %s (no complete checkpoint to resume from)", spec.name, train_dir)
        shutil.rmtree(train_dir)


def train_environment(threads: int) -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    env[IN_MEMORY_DATA_ENV] = "1"  # LeRobot-DP reads its data the way pacdp does (lerobot_pacdp.train_hooks)
    env.setdefault("HF_HUB_OFFLINE", "1")  # every dataset of a study is local
    return env


def open_log(spec: RunSpec, output_dir: Path, state: RunState, command: list[str]) -> IO[str]:
    """The run's `train.log`, opened for appending, with a header line for this call."""
    log = open(spec.run_dir(output_dir) / LOG_FILE, "a")  # noqa: SIM115  (the caller's process writes to it)
    log.write(f"{CALL_HEADER}{time.strftime('%Y-%m-%d %H:%M:%S')} {state.status} at step {state.step}: {shlex.join(command)}\n")
    log.flush()
    return log


def log_tail(spec: RunSpec, output_dir: Path, lines: int = 15) -> str:
    log = spec.run_dir(output_dir) / LOG_FILE
    return "\n  ".join(log.read_text(errors="replace").splitlines()[-lines:]) if log.is_file() else ""


def progress_step(log_path: Path, start_step: int) -> int | None:
    """The training step of the lerobot-train call that started at `start_step`, from the progress bar it shows
    last in its part of the log: the bar (tqdm `N/TOTAL [`) counts the steps since the call's start."""
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 8192))
            tail = f.read().decode(errors="replace")
    except OSError:
        return None
    found = re.findall(r"(\d+)/(\d+) \[", tail.rsplit(CALL_HEADER, 1)[-1])
    return start_step + int(found[-1][0]) if found else None


def format_duration(seconds: float) -> str:
    seconds = int(max(0, seconds))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


def _reached_step(spec: RunSpec, output_dir: Path) -> int | None:
    last = last_checkpoint(spec.train_dir(output_dir))
    return None if last is None else checkpoint_step(last)


@dataclass
class _Active:
    spec: RunSpec
    process: subprocess.Popen
    log: IO[str]
    started: float
    start_step: int
    stop_at: int  # the checkpoint step at which this call stops (== steps unless chunked)
    stopped_by_us: bool = False


@dataclass
class _Tally:
    done: list[RunSpec] = field(default_factory=list)
    paused: list[RunSpec] = field(default_factory=list)
    failed: list[RunSpec] = field(default_factory=list)

    def outcome(self) -> Outcome:
        return Outcome(tuple(self.done), tuple(self.paused), tuple(self.failed))


class LocalExecutor:
    """Runs the planned lerobot-train calls as local subprocesses, `jobs` at a time (CPU threads split
    between them), resumably, with progress a researcher can check; `max_chunk_steps` stops each call at the
    first checkpoint that many steps on (rerun to continue)."""

    def __init__(self, output_dir: Path, trainer: list[str], jobs: int, max_chunk_steps: int | None = None):
        self.output_dir, self.trainer, self.jobs = output_dir, trainer, jobs
        self.max_chunk_steps = max_chunk_steps
        self.threads = max(1, (os.cpu_count() or 1) // jobs)
        self.seconds_per_step: list[float] = []

    def _stop_at(self, spec: RunSpec, start_step: int) -> int:
        if self.max_chunk_steps is None:
            return spec.steps
        target = math.ceil((start_step + self.max_chunk_steps) / spec.save_freq) * spec.save_freq
        return min(spec.steps, target)

    def start(self, spec: RunSpec, state: RunState) -> _Active:
        clear_unstarted(spec, self.output_dir, state)
        command = train_command(spec, self.output_dir, self.trainer, state)
        log = open_log(spec, self.output_dir, state, command)
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=train_environment(self.threads),
                                   start_new_session=True)  # fmt: skip
        return _Active(spec, process, log, time.monotonic(), state.step, self._stop_at(spec, state.step))

    def _stop(self, active: _Active) -> None:
        active.stopped_by_us = True
        os.killpg(active.process.pid, signal.SIGTERM)
        try:
            active.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(active.process.pid, signal.SIGKILL)
            active.process.wait()

    def run(self, specs: list[RunSpec]) -> Outcome:
        """Train every unfinished run of `specs`."""
        tally, pending = _Tally(), []
        for spec in specs:
            if run_state(spec, self.output_dir).status == "done":
                if not (spec.run_dir(self.output_dir) / DONE_FILE).is_file():
                    mark_done(spec, self.output_dir, None)
                tally.done.append(spec)
            else:
                pending.append(spec)
        total = len(specs)
        logger.info("%d runs planned: %d already finished (skipped), %d to train, %d at a time (%d threads each)",
                    total, len(tally.done), len(pending), self.jobs, self.threads)  # fmt: skip
        active: list[_Active] = []
        study_start = last_beat = time.monotonic()
        try:
            while pending or active:
                while pending and len(active) < self.jobs:
                    spec = pending.pop(0)
                    state = run_state(spec, self.output_dir)
                    run = self.start(spec, state)
                    active.append(run)
                    logger.info("[start] %s/%s: %s from step %d to %d of %d (log: %s)", spec.task, spec.name,
                                "resuming" if state.status == "resume" else "training", state.step, run.stop_at,
                                spec.steps, spec.run_dir(self.output_dir) / LOG_FILE)  # fmt: skip
                time.sleep(POLL_S)
                for run in list(active):
                    if run.process.poll() is None and run.stop_at < run.spec.steps:
                        reached = _reached_step(run.spec, self.output_dir)
                        if reached is not None and reached >= run.stop_at:
                            self._stop(run)
                    if run.process.poll() is None:
                        continue
                    active.remove(run)
                    self._finish(run, tally, total)
                if active and time.monotonic() - last_beat >= HEARTBEAT_S:
                    last_beat = time.monotonic()
                    self._heartbeat(active, pending, tally, total, study_start)
        except KeyboardInterrupt:
            for run in active:
                self._stop(run)
                run.log.close()
            logger.warning("interrupted: %d runs stopped; rerun the same command to resume them.", len(active))
            raise
        return tally.outcome()

    def _finish(self, run: _Active, tally: _Tally, total: int) -> None:
        run.log.close()
        spec, seconds = run.spec, time.monotonic() - run.started
        reached = _reached_step(spec, self.output_dir) or run.start_step
        if reached > run.start_step:
            self.seconds_per_step.append(seconds / (reached - run.start_step))
        rate = f"{seconds / max(1, reached - run.start_step):.2f} s/step incl. start-up"
        if run.process.returncode == 0 and final_checkpoint(spec.train_dir(self.output_dir), spec.steps):
            mark_done(spec, self.output_dir, seconds)
            tally.done.append(spec)
            logger.info("[done] %s/%s in %s (%s); %d/%d runs finished", spec.task, spec.name,
                        format_duration(seconds), rate, len(tally.done), total)  # fmt: skip
        elif run.stopped_by_us or -run.process.returncode in STOP_SIGNALS:
            tally.paused.append(spec)
            by = "" if run.stopped_by_us else f" (stopped by {signal.Signals(-run.process.returncode).name})"
            logger.info("[paused] %s/%s at step %d of %d after %s (%s)%s; rerun to continue", spec.task, spec.name,
                        reached, spec.steps, format_duration(seconds), rate, by)  # fmt: skip
        else:
            tally.failed.append(spec)
            logger.error("[FAILED] %s/%s: lerobot-train exited with %s at step %d; see %s. Last lines:\n  %s",
                         spec.task, spec.name, run.process.returncode, reached,
                         spec.run_dir(self.output_dir) / LOG_FILE, log_tail(spec, self.output_dir))  # fmt: skip

    def _heartbeat(self, active: list[_Active], pending: list[RunSpec], tally: _Tally, total: int, start: float) -> None:
        parts, left, rates = [], [], []
        for run in active:
            step = progress_step(run.spec.run_dir(self.output_dir) / LOG_FILE, run.start_step) or run.start_step
            elapsed = time.monotonic() - run.started
            rate = elapsed / (step - run.start_step) if step > run.start_step else None
            parts.append(f"{run.spec.name} step {step}/{run.stop_at}" + (f" ({rate:.2f} s/step)" if rate else ""))
            left.append((run.stop_at - step, rate))
            if rate:
                rates.append(rate)
        known = self.seconds_per_step or rates
        eta = ""
        if known:
            per_step = sorted(known)[len(known) // 2]
            running = [steps * (rate or per_step) for steps, rate in left]
            waiting = []
            for spec in pending:
                step = run_state(spec, self.output_dir).step
                waiting.append((self._stop_at(spec, step) - step) * per_step)
            eta = f"; estimated time left ~{format_duration(time_left(running, waiting, self.jobs))}"
        logger.info("[progress %s] %d/%d finished, %d running, %d waiting%s | %s",
                    format_duration(time.monotonic() - start), len(tally.done), total, len(active), len(pending),
                    eta, " | ".join(parts))  # fmt: skip
