"""`--executor=slurm`: a study's runs as a SLURM job array, through submitit.

Each job of the array is one run: one lerobot-train call (through `accelerate launch` on more than one GPU,
LeRobot's multi-GPU path) that trains it from its request or resumes it from its last complete checkpoint.
On preemption or at the time limit SLURM signals the job (submitit asks for `USR2` 90 s before); the job
stops lerobot-train and submitit requeues it, and the requeued job resumes from the last complete
checkpoint. Submitting the study again skips finished runs, runs whose job is still queued or running, and
resumes the others; `pacdp-study ... --train=false` reads where every run stands from the run directories.
"""

import logging
import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from lerobot_pacdp.study.executors import (
    Outcome,
    clear_unstarted,
    log_tail,
    open_log,
    train_command,
    train_environment,
)
from lerobot_pacdp.study.plan import RunSpec
from lerobot_pacdp.study.presets import StudyError
from lerobot_pacdp.study.state import (
    DONE_FILE,
    JOB_FILE,
    LOG_FILE,
    mark_done,
    run_state,
    submitted_job,
    write_json_atomic,
)
from lerobot_pacdp.train_runs import final_checkpoint

logger = logging.getLogger("pacdp-study")

POLL_S = 1.0
STOP_GRACE_S = 60.0  # SIGTERM, then SIGKILL: well inside the 90 s SLURM leaves between its signal and the kill
CLUSTERS = ("slurm", "local", "debug")  # submitit's: SLURM, or this machine (local subprocesses, in-process)
# SLURM states of a job that has not ended: resubmitting its run would train it twice at once.
ACTIVE_STATES = {"PENDING", "RUNNING", "REQUEUED", "CONFIGURING", "COMPLETING", "RESIZING", "SUSPENDED",
                 "REQUEUE_HOLD", "REQUEUE_FED", "SIGNALING", "STAGE_OUT"}  # fmt: skip


@dataclass
class SlurmOptions:
    """`--slurm.*`: the resources of every job of the array (one job per run)."""

    partition: str | None = None
    account: str | None = None
    qos: str | None = None
    gpus_per_node: int = 1  # more than 1: lerobot-train through `accelerate launch --multi_gpu`
    cpus_per_task: int = 8
    mem_gb: float = 64.0
    timeout_min: int = 24 * 60  # per job; a run that needs longer is requeued and resumes
    array_parallelism: int = 256  # jobs of the array running at once
    max_timeouts: int = 20  # requeues after reaching the time limit before a run is given up (preemptions: no limit)
    folder: Path | None = None  # submitit's job files and logs (default: <output_dir>/slurm)
    wait: bool = False  # stay until every job has ended (then the metrics and tables follow)
    cluster: str = "slurm"  # submitit's cluster: `local` or `debug` run the jobs on this machine (tests)

    def validate(self) -> None:
        if self.cluster not in CLUSTERS:
            raise StudyError(f"--slurm.cluster must be one of {', '.join(CLUSTERS)}, got {self.cluster!r}.")
        if self.gpus_per_node < 0:
            raise StudyError(f"--slurm.gpus_per_node must be >= 0, got {self.gpus_per_node}.")
        for name in ("cpus_per_task", "timeout_min", "array_parallelism"):
            if getattr(self, name) < 1:
                raise StudyError(f"--slurm.{name} must be >= 1, got {getattr(self, name)}.")
        if not self.mem_gb > 0:
            raise StudyError(f"--slurm.mem_gb must be > 0, got {self.mem_gb}.")

    def sbatch_parameters(self) -> dict:
        """The array's `#SBATCH` settings, in submitit's SLURM names."""
        params = {"job_name": "pacdp-study", "partition": self.partition, "account": self.account, "qos": self.qos,
                  "nodes": 1, "ntasks_per_node": 1, "gpus_per_node": self.gpus_per_node or None,
                  "cpus_per_task": self.cpus_per_task, "mem": _sbatch_memory(self.mem_gb), "time": self.timeout_min,
                  "array_parallelism": self.array_parallelism}  # fmt: skip
        return {k: v for k, v in params.items() if v is not None}

    def executor_parameters(self) -> dict:
        """The same for submitit's AutoExecutor (generic names, `slurm_*` for SLURM's own)."""
        params = {"name": "pacdp-study", "nodes": 1, "tasks_per_node": 1, "gpus_per_node": self.gpus_per_node,
                  "cpus_per_task": self.cpus_per_task, "mem_gb": self.mem_gb, "timeout_min": self.timeout_min,
                  "slurm_partition": self.partition, "slurm_account": self.account, "slurm_qos": self.qos,
                  "slurm_array_parallelism": self.array_parallelism}  # fmt: skip
        return {k: v for k, v in params.items() if v is not None}


def _sbatch_memory(mem_gb: float) -> str:
    return f"{int(mem_gb)}GB" if mem_gb == int(mem_gb) else f"{int(mem_gb * 1024)}MB"


def accelerate_launcher(gpus_per_node: int) -> list[str]:
    """The prefix that runs lerobot-train on every GPU of the node (LeRobot's multi-GPU path); none for one."""
    if gpus_per_node <= 1:
        return []
    accelerate = Path(sys.executable).parent / "accelerate"
    return [str(accelerate), "launch", "--multi_gpu", f"--num_processes={gpus_per_node}"]


class TrainJob:
    """One job of the array: train or resume one run; on preemption, stop lerobot-train and requeue.

    submitit pickles it, runs it on a compute node and, when SLURM signals the job, calls `checkpoint`,
    whose returned submission is what the requeued job runs.
    """

    def __init__(self, spec: RunSpec, output_dir: Path, trainer: list[str], launcher: list[str], threads: int):
        self.spec, self.output_dir, self.trainer, self.launcher, self.threads = spec, output_dir, trainer, launcher, threads
        self._process: subprocess.Popen | None = None

    def __call__(self) -> str:
        spec, output_dir = self.spec, self.output_dir
        state = run_state(spec, output_dir)
        if state.status == "done":
            return "done"
        clear_unstarted(spec, output_dir, state)
        command = [*self.launcher, *train_command(spec, output_dir, self.trainer, state)]
        started = time.monotonic()
        with open_log(spec, output_dir, state, command) as log:
            self._process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                             env=train_environment(self.threads), start_new_session=True)  # fmt: skip
            # Polled, not waited for: `checkpoint` runs in a signal handler on this thread and must not block
            # on the lock a pending `Popen.wait` holds.
            while (returncode := self._process.poll()) is None:
                time.sleep(POLL_S)
        if returncode == 0 and final_checkpoint(spec.train_dir(output_dir), spec.steps) is not None:
            mark_done(spec, output_dir, time.monotonic() - started)
            return "done"
        raise RuntimeError(
            f"lerobot-train exited with {returncode} for {spec.task}/{spec.name} at step "
            f"{run_state(spec, output_dir).step}; see {spec.run_dir(output_dir) / LOG_FILE}. Last lines:\n  "
            f"{log_tail(spec, output_dir)}"
        )

    def checkpoint(self):
        """Called by submitit when SLURM preempts the job or its time is nearly up: stop lerobot-train (its last
        complete checkpoint stays) and requeue this run; the requeued job resumes from that checkpoint."""
        import submitit

        process = self._process
        if process is not None and process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
            deadline = time.monotonic() + STOP_GRACE_S
            while process.poll() is None and time.monotonic() < deadline:
                time.sleep(0.1)
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
        return submitit.helpers.DelayedSubmission(TrainJob(self.spec, self.output_dir, self.trainer, self.launcher,
                                                           self.threads))  # fmt: skip

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_process"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _process=None)


def job_state(record: dict) -> str:
    """SLURM's state of a recorded job (`sacct`, through submitit); UNKNOWN when it cannot be asked."""
    import submitit

    try:
        return submitit.SlurmJob(folder=record["folder"], job_id=record["job_id"]).state
    except Exception:  # no sacct on this machine, a purged job: treat it as ended
        return "UNKNOWN"


class SlurmExecutor:
    """Submits every unfinished run of a study as one SLURM job array (submitit's AutoExecutor)."""

    def __init__(self, output_dir: Path, trainer: list[str], options: SlurmOptions):
        options.validate()
        self.output_dir, self.trainer, self.options = output_dir, trainer, options
        self.folder = options.folder or output_dir / "slurm"

    def job(self, spec: RunSpec) -> TrainJob:
        launcher = accelerate_launcher(self.options.gpus_per_node)
        return TrainJob(spec, self.output_dir, self.trainer, launcher, self.options.cpus_per_task)

    def _still_queued(self, spec: RunSpec) -> str | None:
        """The job id of a run whose SLURM job has not ended, else None."""
        record = submitted_job(spec, self.output_dir)
        if record is None or record.get("cluster") != "slurm" or self.options.cluster != "slurm":
            return None
        return record["job_id"] if job_state(record) in ACTIVE_STATES else None

    def _to_submit(self, specs: list[RunSpec]) -> tuple[list[RunSpec], list[RunSpec], list[RunSpec]]:
        """(done, still queued or running, to submit)."""
        done, queued, todo = [], [], []
        for spec in specs:
            if run_state(spec, self.output_dir).status == "done":
                if not (spec.run_dir(self.output_dir) / DONE_FILE).is_file():
                    mark_done(spec, self.output_dir, None)
                done.append(spec)
            elif (job_id := self._still_queued(spec)) is not None:
                logger.info("  %s/%s: still queued or running as SLURM job %s; not submitted again", spec.task,
                            spec.name, job_id)  # fmt: skip
                queued.append(spec)
            else:
                todo.append(spec)
        return done, queued, todo

    def preview(self, specs: list[RunSpec]) -> str:
        """What `run` would submit: the array's sbatch parameters and each job's run, state and command."""
        from submitit.slurm.slurm import _make_sbatch_string

        done, queued, todo = self._to_submit(specs)
        lines = [f"SLURM job array: {len(todo)} jobs ({len(done)} runs done, {len(queued)} still queued or running)"]
        if todo:
            header = _make_sbatch_string(
                command="python -u -m submitit.core._submit " + shlex.quote(str(self.folder)),
                folder=self.folder, map_count=len(todo), **self.options.sbatch_parameters(),
            )  # fmt: skip
            lines += [line for line in header.splitlines() if line.startswith("#SBATCH")]
        parameters = self.options.sbatch_parameters()
        shown = " ".join(f"{k}={v}" for k, v in parameters.items() if k not in ("job_name", "array_parallelism"))
        for index, spec in enumerate(todo):
            state = run_state(spec, self.output_dir)
            where = "new" if state.status == "new" else f"resume from step {state.step}"
            command = [*accelerate_launcher(self.options.gpus_per_node), *train_command(spec, self.output_dir,
                                                                                       self.trainer, state)]
            lines.append(f"job {index}: {spec.task}/{spec.name} ({where}) {shown}")
            lines.append(f"  {shlex.join(command)}")
        return "\n".join(lines)

    def run(self, specs: list[RunSpec]) -> Outcome:
        import submitit

        done, queued, todo = self._to_submit(specs)
        logger.info("%d runs planned: %d already finished, %d still queued or running, %d to submit",
                    len(specs), len(done), len(queued), len(todo))  # fmt: skip
        if not todo:
            return Outcome(done=tuple(done), submitted=tuple(queued))
        executor = submitit.AutoExecutor(folder=self.folder, cluster=self.options.cluster,
                                         slurm_max_num_timeout=self.options.max_timeouts)  # fmt: skip
        executor.update_parameters(**self.options.executor_parameters())
        jobs = executor.submit_array([self.job(spec) for spec in todo])
        for spec, job in zip(todo, jobs, strict=True):
            write_json_atomic(spec.run_dir(self.output_dir) / JOB_FILE,
                              {"job_id": job.job_id, "cluster": self.options.cluster, "folder": str(self.folder),
                               "submitted": time.strftime("%Y-%m-%d %H:%M:%S")})  # fmt: skip
        logger.info("submitted %d runs as %s; job files and logs in %s", len(jobs),
                    f"SLURM array {str(jobs[0].job_id).split('_')[0]}" if self.options.cluster == "slurm"
                    else f"{self.options.cluster} jobs", self.folder)  # fmt: skip
        if not (self.options.wait or self.options.cluster != "slurm"):
            return Outcome(done=tuple(done), submitted=(*queued, *todo))
        failed = []
        for spec, job in zip(todo, jobs, strict=True):
            error = job.exception()  # waits; the job's error (or submitit's, for a killed job), else None
            if error is None:
                done.append(spec)
                logger.info("[done] %s/%s", spec.task, spec.name)
            else:
                failed.append(spec)
                logger.error("[FAILED] %s/%s (job %s): %s", spec.task, spec.name, job.job_id, str(error).strip()[-3000:])
        return Outcome(done=tuple(done), failed=tuple(failed), submitted=tuple(queued))
