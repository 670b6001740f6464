"""`pacdp-study`: the DP vs BDP vs PAC-DP reproduction study (paper Sec. IV), resumable, in one command.

    pacdp-study --preset=cpu --output_dir=outputs/study_cpu            # ~1 h on 2 CPU cores
    pacdp-study --preset=cpu --output_dir=outputs/study_cpu --dry_run=true
    pacdp-study --preset=cpu --output_dir=outputs/study_long --long_pair=true --jobs=3  # 6k more steps per call
    pacdp-study --preset=paper --output_dir=outputs/study_paper --tasks=[pusht] --seeds=[0,1,2]

Plan: tasks x demos x seeds x {DP, BDP per rho, PAC-DP per (lambda, rho)}. For each seed one held-out
set of demos is drawn, disjoint from every training set of that seed; the training demos of (demos,
seed) are the first `demos` of the remaining ones in a seeded order, so they are identical for every
method and nested (the 20 are among the 40). Every run is a `lerobot-train` subprocess with its own
output dir; a run whose final checkpoint exists is skipped, an interrupted one resumes from its last
checkpoint (`--resume=true`). Then the metrics (NPE, NLL bound, success rate) and the tables/plots.
"""

import copy
import dataclasses
import json
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
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.train_hooks import IN_MEMORY_DATA_ENV
from lerobot_pacdp.study.presets import Preset, StudyError, TaskPreset, get_preset, validate, with_overrides

logger = logging.getLogger("pacdp-study")

# DP is pacdp's `bayesian=false` twin (PAC-DP minus what the paper changes); LeRobot-DP, LeRobot's own
# `diffusion` policy with the same settings, is an extra (`--lerobot_diffusion=true`).
METHODS = ("DP", "BDP", "PAC-DP", "LeRobot-DP")
SPLIT_SALT = 20_260_523  # decorrelates the episode order from the training seed
REQUEST_FILE, DONE_FILE, LOG_FILE = "train_request.json", "done.json", "train.log"
POLL_S, HEARTBEAT_S = 2.0, 60.0
# A run stopped by one of these (a user or scheduler ending it, not a crash) is paused: rerunning resumes it.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


@dataclass(frozen=True)
class RunSpec:
    """One lerobot-train run of the study."""

    task: str
    demos: int
    seed: int
    method: str  # one of METHODS
    kl_weight: float | None  # None for DP
    prior_rho: float | None  # None for DP
    steps: int
    save_freq: int
    train_episodes: tuple[int, ...]
    heldout_episodes: tuple[int, ...]
    group: str = "main"  # "main" or "long" (the long BDP / PAC-DP pair)

    @property
    def name(self) -> str:
        if self.method == "DP":
            tag = "dp"
        elif self.method == "LeRobot-DP":
            tag = "lerobot_dp"
        elif self.method == "BDP":
            tag = f"bdp_rho{self.prior_rho:g}"
        else:
            tag = f"pacdp_kl{self.kl_weight:g}_rho{self.prior_rho:g}"
        return f"d{self.demos:03d}_s{self.seed}_{tag}"

    def run_dir(self, output_dir: Path) -> Path:
        return output_dir / "runs" / self.task / self.group / self.name

    def train_dir(self, output_dir: Path) -> Path:
        return self.run_dir(output_dir) / "train"


# ---------------------------------------------------------------------------------------------- planning


def split_episodes(num_episodes: int, seed: int, heldout: int, demos: Sequence[int]) -> tuple[list[int], dict[int, list[int]]]:
    """(held-out demos, {demos: training demos}) for one seed.

    One seeded permutation: its first `heldout` entries are held out, the training set of size d is the
    next d. So the held-out set does not depend on `demos` or the method, never meets a training set,
    and training sets are nested.
    """
    if heldout < 1:
        raise StudyError(f"the held-out set needs at least one demo, got heldout={heldout}.")
    pool = num_episodes - heldout
    too_many = [d for d in demos if d > pool]
    if too_many:
        raise StudyError(
            f"{num_episodes} demos with {heldout} held out leave {pool} for training; cannot train on {too_many}."
        )
    order = np.random.default_rng([SPLIT_SALT, seed]).permutation(num_episodes).tolist()
    held, rest = sorted(order[:heldout]), order[heldout:]
    return held, {d: sorted(rest[:d]) for d in demos}


def plan_task(
    task: TaskPreset, preset: Preset, num_episodes: int, long_pair: bool = False, lerobot_diffusion: bool = False
) -> list[RunSpec]:
    """The runs of one task; with `long_pair`, BDP and PAC-DP at the reference point, and DP beside them
    (the long runs must show where DP's held-out NPE turns up, and whether the KL term then separates
    PAC-DP from BDP); with `lerobot_diffusion`, LeRobot's own diffusion policy beside DP."""
    kl_grid = [task.reference_kl_weight] + [k for k in preset.kl_weights if k != task.reference_kl_weight]
    rho_grid = list(preset.prior_rhos)
    if long_pair:
        points = [("DP", None, None), ("BDP", 0.0, preset.reference_rho),
                  ("PAC-DP", task.reference_kl_weight, preset.reference_rho)]  # fmt: skip
    else:
        points = [("DP", None, None)] + [("BDP", 0.0, r) for r in rho_grid]
        points += [("PAC-DP", k, r) for k in kl_grid for r in rho_grid]
    if lerobot_diffusion:
        points.insert(1, ("LeRobot-DP", None, None))
    runs = []
    for seed in preset.seeds:
        heldout, train_sets = split_episodes(num_episodes, seed, task.heldout, task.demos)
        for demos in task.demos:
            for method, kl, rho in points:
                runs.append(
                    RunSpec(task.name, demos, seed, method, kl, rho, task.steps, task.save_freq,
                            tuple(train_sets[demos]), tuple(heldout), "long" if long_pair else "main")
                )  # fmt: skip
    return runs


# ------------------------------------------------------------------------------------ train configs


def _diffusion_policy(pacdp_policy: dict) -> dict:
    """LeRobot `diffusion` settings equal to a `pacdp` policy's: the same U-Net, schedule, inference and
    normalisation, without the PAC-Bayes fields (PacdpConfig's defaults differ from DiffusionConfig's)."""
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    from lerobot_pacdp.configuration_pacdp import PacdpConfig

    shared = [f.name for f in dataclasses.fields(DiffusionConfig) if f.init]
    pacdp_defaults, dp_defaults = draccus.encode(PacdpConfig()), draccus.encode(DiffusionConfig())
    policy = {"type": "diffusion"}
    policy.update({k: pacdp_defaults[k] for k in shared if pacdp_defaults[k] != dp_defaults[k]})
    policy.update({k: v for k, v in pacdp_policy.items() if k in shared})
    return policy


def train_config(spec: RunSpec, task: TaskPreset, dataset_root: Path | None, seed_offset: int, output_dir: Path) -> dict:
    """The complete lerobot-train config of one run (written to its run dir as `train_request.json`)."""
    config = copy.deepcopy(task.train_config)
    config["dataset"].update(episodes=list(spec.train_episodes), eval_split=0.0)
    if dataset_root is not None:
        config["dataset"]["root"] = str(dataset_root)
    policy = config["policy"]
    if spec.method == "LeRobot-DP":
        config["policy"] = _diffusion_policy({k: v for k, v in policy.items() if k != "type"})
    elif spec.method == "DP":
        policy.update(type="pacdp", bayesian=False)
    else:
        policy.update(type="pacdp", kl_weight=spec.kl_weight, prior_rho=spec.prior_rho)
    # The held-out demos are evaluated by the metrics sweep, not by lerobot-train's eval split.
    config.update(steps=spec.steps, save_freq=spec.save_freq, seed=seed_offset + spec.seed, eval_steps=0,
                  env_eval_freq=0, output_dir=str(spec.train_dir(output_dir)), wandb={"enable": False})  # fmt: skip
    return config


def write_json_atomic(path: Path, content) -> None:
    """JSON through `write_text_atomic`: readers never see a half-written file."""
    write_text_atomic(path, json.dumps(content, indent=2) + "\n")


# ------------------------------------------------------------------------------------------- run state


def checkpoint_complete(step_dir: Path) -> bool:
    return (step_dir / "pretrained_model" / "model.safetensors").is_file() and (
        step_dir / "training_state" / "training_step.json"
    ).is_file()


def final_checkpoint(train_dir: Path, steps: int) -> Path | None:
    """The run's checkpoint at its last step, if lerobot-train finished writing it."""
    checkpoints = train_dir / "checkpoints"
    if checkpoints.is_dir():
        for step_dir in checkpoints.iterdir():
            if step_dir.name.isdigit() and int(step_dir.name) == steps and checkpoint_complete(step_dir):
                return step_dir
    return None


def last_checkpoint_step(train_dir: Path) -> int | None:
    """Step of `checkpoints/last` (lerobot-train points it at a checkpoint only once that is written)."""
    last = train_dir / "checkpoints" / "last"
    if not last.is_symlink() or not checkpoint_complete(last):
        return None
    return int(json.loads((last / "training_state" / "training_step.json").read_text())["step"])


def run_status(spec: RunSpec, output_dir: Path) -> tuple[str, int]:
    """("done" | "resume" | "new", last completed step)."""
    run_dir, train_dir = spec.run_dir(output_dir), spec.train_dir(output_dir)
    if (run_dir / DONE_FILE).is_file() or final_checkpoint(train_dir, spec.steps) is not None:
        return "done", spec.steps
    step = last_checkpoint_step(train_dir)
    return ("resume", step) if step is not None else ("new", 0)


def mark_done(spec: RunSpec, output_dir: Path, seconds: float | None) -> None:
    final = final_checkpoint(spec.train_dir(output_dir), spec.steps)
    write_json_atomic(
        spec.run_dir(output_dir) / DONE_FILE,
        {"run": spec.name, "steps": spec.steps, "final_checkpoint": str(final), "last_call_seconds": seconds,
         "finished": time.strftime("%Y-%m-%d %H:%M:%S")},
    )  # fmt: skip


# ------------------------------------------------------------------------------------------- execution


def default_trainer() -> list[str]:
    local = Path(sys.executable).parent / "lerobot-train"
    found = str(local) if local.exists() else shutil.which("lerobot-train")
    if found is None:
        raise StudyError("lerobot-train is not on PATH; install lerobot (pip install -e .) in this environment.")
    return [found]


@dataclass
class Active:
    spec: RunSpec
    process: subprocess.Popen
    log: object
    started: float
    start_step: int
    stop_at: int  # the checkpoint step at which this call stops (== steps unless chunked)
    stopped_by_us: bool = False


def _progress_step(log_path: Path) -> int | None:
    """The training step lerobot-train's progress bar shows last (tqdm `N/TOTAL [`)."""
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 8192))
            tail = f.read().decode(errors="replace")
    except OSError:
        return None
    found = re.findall(r"(\d+)/(\d+) \[", tail)
    return int(found[-1][0]) if found else None


def _fmt_s(seconds: float) -> str:
    seconds = int(max(0, seconds))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


class Executor:
    """Runs the planned lerobot-train calls, `jobs` at a time, resumably, with progress a researcher can check."""

    def __init__(self, preset: Preset, output_dir: Path, trainer: list[str], max_chunk_steps: int | None):
        self.preset, self.output_dir, self.trainer = preset, output_dir, trainer
        self.max_chunk_steps = max_chunk_steps
        self.threads = max(1, (os.cpu_count() or 1) // preset.jobs)
        self.seconds_per_step: list[float] = []

    def _command(self, spec: RunSpec, status: str) -> list[str]:
        run_dir = spec.run_dir(self.output_dir)
        if status == "resume":
            config = spec.train_dir(self.output_dir) / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
            return [*self.trainer, f"--config_path={config}", "--resume=true"]
        return [*self.trainer, f"--config_path={run_dir / REQUEST_FILE}"]

    def _stop_at(self, spec: RunSpec, start_step: int) -> int:
        if self.max_chunk_steps is None:
            return spec.steps
        target = math.ceil((start_step + self.max_chunk_steps) / spec.save_freq) * spec.save_freq
        return min(spec.steps, target)

    def start(self, spec: RunSpec, status: str, step: int) -> Active:
        train_dir = spec.train_dir(self.output_dir)
        if status == "new" and train_dir.exists():  # died before its first checkpoint: nothing to resume
            logger.info("  %s: removing %s (no complete checkpoint to resume from)", spec.name, train_dir)
            shutil.rmtree(train_dir)
        command = self._command(spec, status)
        log = open(spec.run_dir(self.output_dir) / LOG_FILE, "a")
        log.write(f"\n===== {time.strftime('%Y-%m-%d %H:%M:%S')} {status} at step {step}: {shlex.join(command)}\n")
        log.flush()
        env = {**os.environ, "OMP_NUM_THREADS": str(self.threads), "MKL_NUM_THREADS": str(self.threads)}
        env[IN_MEMORY_DATA_ENV] = "1"  # LeRobot-DP reads its data the way pacdp does (lerobot_pacdp.train_hooks)
        env.setdefault("HF_HUB_OFFLINE", "1")  # every dataset of a study is local
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        return Active(spec, process, log, time.monotonic(), step, self._stop_at(spec, step))

    def _stop(self, active: Active) -> None:
        active.stopped_by_us = True
        os.killpg(active.process.pid, signal.SIGTERM)
        try:
            active.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(active.process.pid, signal.SIGKILL)
            active.process.wait()

    def run(self, specs: list[RunSpec]) -> dict[str, list[RunSpec]]:
        """Train every unfinished run; returns {"done": [...], "paused": [...], "failed": [...]}."""
        outcome: dict[str, list[RunSpec]] = {"done": [], "paused": [], "failed": []}
        pending = []
        for spec in specs:
            status, step = run_status(spec, self.output_dir)
            if status == "done":
                if not (spec.run_dir(self.output_dir) / DONE_FILE).is_file():
                    mark_done(spec, self.output_dir, None)
                outcome["done"].append(spec)
            else:
                pending.append(spec)
        total = len(specs)
        logger.info("%d runs planned: %d already finished (skipped), %d to train, %d at a time (%d threads each)",
                    total, len(outcome["done"]), len(pending), self.preset.jobs, self.threads)  # fmt: skip
        active: list[Active] = []
        study_start, last_beat = time.monotonic(), time.monotonic()
        try:
            while pending or active:
                while pending and len(active) < self.preset.jobs:
                    spec = pending.pop(0)
                    status, step = run_status(spec, self.output_dir)
                    run = self.start(spec, status, step)
                    active.append(run)
                    logger.info("[start] %s/%s: %s from step %d to %d of %d (log: %s)", spec.task, spec.name,
                                "resuming" if status == "resume" else "training", step, run.stop_at, spec.steps,
                                spec.run_dir(self.output_dir) / LOG_FILE)  # fmt: skip
                time.sleep(POLL_S)
                for run in list(active):
                    train_dir = run.spec.train_dir(self.output_dir)
                    if run.process.poll() is None and run.stop_at < run.spec.steps:
                        reached = last_checkpoint_step(train_dir)
                        if reached is not None and reached >= run.stop_at:
                            self._stop(run)
                    if run.process.poll() is None:
                        continue
                    active.remove(run)
                    self._finish(run, outcome, total)
                if active and time.monotonic() - last_beat >= HEARTBEAT_S:
                    last_beat = time.monotonic()
                    self._heartbeat(active, pending, outcome, total, study_start)
        except KeyboardInterrupt:
            for run in active:
                self._stop(run)
                run.log.close()
            logger.warning("interrupted: %d runs stopped; rerun the same command to resume them.", len(active))
            raise
        return outcome

    def _finish(self, run: Active, outcome: dict[str, list[RunSpec]], total: int) -> None:
        run.log.close()
        spec, seconds = run.spec, time.monotonic() - run.started
        reached = last_checkpoint_step(spec.train_dir(self.output_dir)) or run.start_step
        if reached > run.start_step:
            self.seconds_per_step.append(seconds / (reached - run.start_step))
        rate = f"{seconds / max(1, reached - run.start_step):.2f} s/step incl. start-up"
        if run.process.returncode == 0 and final_checkpoint(spec.train_dir(self.output_dir), spec.steps):
            mark_done(spec, self.output_dir, seconds)
            outcome["done"].append(spec)
            logger.info("[done] %s/%s in %s (%s); %d/%d runs finished", spec.task, spec.name, _fmt_s(seconds), rate,
                        len(outcome["done"]), total)  # fmt: skip
        elif run.stopped_by_us or -run.process.returncode in STOP_SIGNALS:
            outcome["paused"].append(spec)
            by = "" if run.stopped_by_us else f" (stopped by {signal.Signals(-run.process.returncode).name})"
            logger.info("[paused] %s/%s at step %d of %d after %s (%s)%s; rerun to continue", spec.task, spec.name,
                        reached, spec.steps, _fmt_s(seconds), rate, by)  # fmt: skip
        else:
            outcome["failed"].append(spec)
            log = spec.run_dir(self.output_dir) / LOG_FILE
            tail = log.read_text(errors="replace").splitlines()[-15:]
            logger.error("[FAILED] %s/%s: lerobot-train exited with %s at step %d; see %s. Last lines:\n  %s",
                         spec.task, spec.name, run.process.returncode, reached, log, "\n  ".join(tail))  # fmt: skip

    def _heartbeat(self, active: list[Active], pending: list[RunSpec], outcome: dict, total: int, start: float) -> None:
        parts, remaining = [], 0.0
        for run in active:
            step = _progress_step(run.spec.run_dir(self.output_dir) / LOG_FILE) or run.start_step
            elapsed = time.monotonic() - run.started
            rate = elapsed / (step - run.start_step) if step > run.start_step else None
            parts.append(f"{run.spec.name} step {step}/{run.stop_at}" + (f" ({rate:.2f} s/step)" if rate else ""))
            if rate:
                remaining += (run.stop_at - step) * rate
        known = self.seconds_per_step or [
            (time.monotonic() - r.started) / (s - r.start_step)
            for r in active if (s := _progress_step(r.spec.run_dir(self.output_dir) / LOG_FILE) or 0) > r.start_step
        ]  # fmt: skip
        eta = ""
        if known:
            per_step = sorted(known)[len(known) // 2]
            todo = sum(self._stop_at(s, run_status(s, self.output_dir)[1]) - run_status(s, self.output_dir)[1] for s in pending)
            eta = f"; estimated time left ~{_fmt_s((remaining + todo * per_step) / self.preset.jobs)}"
        logger.info("[progress %s] %d/%d finished, %d running, %d waiting%s | %s", _fmt_s(time.monotonic() - start),
                    len(outcome["done"]), total, len(active), len(pending), eta, " | ".join(parts))  # fmt: skip


# -------------------------------------------------------------------------------------------- datasets


def dataset_root(task: TaskPreset, output_dir: Path) -> Path | None:
    """Where the task's dataset lives (None: LeRobot's default location for its repo id)."""
    if task.dataset_root is None:
        return None
    root = Path(task.dataset_root)
    return root if root.is_absolute() else output_dir / root


def _dataset_location(task: TaskPreset, output_dir: Path) -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return dataset_root(task, output_dir) or HF_LEROBOT_HOME / task.repo_id


def count_episodes(task: TaskPreset, output_dir: Path) -> int:
    """Demos in the task's dataset (or in its PushT source before conversion)."""
    root = _dataset_location(task, output_dir)
    info = root / "meta" / "info.json"
    if info.is_file():
        return int(json.loads(info.read_text())["total_episodes"])
    if task.pusht_zarr is not None:
        from lerobot_pacdp.datasets.pusht_zarr import PushTConversionError, load_replay_buffer

        try:
            return load_replay_buffer(task.pusht_zarr).num_episodes
        except PushTConversionError as exc:
            raise StudyError(str(exc)) from None
    if task.num_episodes is not None:
        return task.num_episodes
    raise StudyError(f"{task.name}: no dataset at {root}; convert its demos there first.")


def prepare_dataset(task: TaskPreset, output_dir: Path) -> None:
    """Convert the PushT demos into the study's output dir once (all of them: indices stay the zarr's)."""
    root = _dataset_location(task, output_dir)
    if (root / "meta" / "info.json").is_file():
        return
    if task.pusht_zarr is None:
        raise StudyError(
            f"{task.name}: the dataset {task.repo_id} is missing at {root}; convert it first "
            "(pacdp-convert-robomimic for robomimic tasks)."
        )
    from lerobot_pacdp.datasets.pusht_zarr import PushTConversionError, convert_pusht_zarr

    logger.info("converting the PushT demos of %s into %s ...", task.pusht_zarr, root)
    start = time.monotonic()
    try:
        convert_pusht_zarr(task.pusht_zarr, root, task.repo_id)
    except PushTConversionError as exc:
        raise StudyError(str(exc)) from None
    logger.info("converted in %s", _fmt_s(time.monotonic() - start))


# ------------------------------------------------------------------------------------------------- CLI


@dataclass
class StudyConfig:
    """`pacdp-study` options (`--flag=value`; lists as `--seeds=[0,1]`). Unset overrides keep the preset's."""

    preset: str = "cpu"  # cpu | paper (see lerobot_pacdp.study.presets)
    output_dir: Path = Path("outputs/study")
    dry_run: bool = False  # print the plan (runs, episodes, what is done / to resume) and exit
    long_pair: bool = False  # instead of the study: the long BDP / PAC-DP pair and DP (reference point, first seed)
    lerobot_diffusion: bool = False  # also train LeRobot's own `diffusion` policy (method LeRobot-DP) beside DP
    tasks: list[str] | None = None
    demos: list[int] | None = None
    seeds: list[int] | None = None
    steps: int | None = None
    save_freq: int | None = None  # default with --steps: steps / 10
    kl_weights: list[float] | None = None  # PAC-DP grid (each task's reference lambda always included)
    prior_rhos: list[float] | None = None  # BDP / PAC-DP rho grid
    jobs: int | None = None  # lerobot-train runs side by side (CPU threads are split between them)
    max_chunk_steps: int | None = None  # stop each run after this many more steps (rerun to continue)
    train: bool = True  # false: only (re)compute metrics and tables of finished runs
    metrics: bool = True  # false: train only
    report_unfinished: bool = False  # also report runs stopped before their last step, up to their last checkpoint
    success_episodes: int | None = None  # rollouts per evaluated checkpoint (0: no success rate)
    perf: bool = False  # also (re)measure the performance table with benchmarks/speed.py
    trainer: str | None = None  # command replacing lerobot-train (for tests); its args are the same


def resolve_preset(cfg: StudyConfig) -> Preset:
    preset = get_preset(cfg.preset)
    if cfg.long_pair:
        if preset.long_pair_steps < 1:
            raise StudyError(f"preset {preset.name!r} defines no long pair.")
        batch = {} if preset.long_pair_batch_size is None else {"batch_size": preset.long_pair_batch_size}
        tasks = tuple(
            dataclasses.replace(t, demos=(preset.long_pair_demos,), steps=preset.long_pair_steps,
                                save_freq=preset.long_pair_save_freq, train_config={**t.train_config, **batch})
            for t in preset.tasks[:1]
        )  # fmt: skip
        preset = dataclasses.replace(preset, tasks=tasks, seeds=preset.seeds[:1])
        validate(preset)
    return with_overrides(
        preset, tasks=cfg.tasks, demos=cfg.demos, seeds=cfg.seeds, steps=cfg.steps, save_freq=cfg.save_freq,
        kl_weights=cfg.kl_weights, prior_rhos=cfg.prior_rhos, jobs=cfg.jobs, success_episodes=cfg.success_episodes,
    )  # fmt: skip


def plan_study(
    preset: Preset, output_dir: Path, long_pair: bool = False, lerobot_diffusion: bool = False
) -> list[RunSpec]:
    return [
        spec
        for task in preset.tasks
        for spec in plan_task(task, preset, count_episodes(task, output_dir), long_pair, lerobot_diffusion)
    ]


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


def format_plan(specs: list[RunSpec], output_dir: Path) -> str:
    lines = []
    for task in dict.fromkeys(s.task for s in specs):
        lines.append(f"task {task}:")
        for seed in dict.fromkeys(s.seed for s in specs if s.task == task):
            runs = [s for s in specs if s.task == task and s.seed == seed]
            lines.append(f"  seed {seed}: held-out demos ({len(runs[0].heldout_episodes)}): {list(runs[0].heldout_episodes)}")
            for demos in dict.fromkeys(s.demos for s in runs):
                first = next(s for s in runs if s.demos == demos)
                lines.append(f"    {demos} training demos (same for every method): {list(first.train_episodes)}")
    lines.append(f"{'run':<42}{'method':<8}{'lambda':>9}{'rho':>7}{'steps':>9}  state")
    for spec in specs:
        status, step = run_status(spec, output_dir)
        state = {"done": "done (skipped)", "resume": f"resume from step {step}", "new": "new"}[status]
        kl = "" if spec.kl_weight is None else f"{spec.kl_weight:g}"
        rho = "" if spec.prior_rho is None else f"{spec.prior_rho:g}"
        lines.append(f"{spec.task + '/' + spec.name:<42}{spec.method:<8}{kl:>9}{rho:>7}{spec.steps:>9}  {state}")
    return "\n".join(lines)


def _setup_logging(output_dir: Path) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    formatter = logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S")
    for handler in (logging.StreamHandler(sys.stdout), logging.FileHandler(output_dir / "study.log")):
        handler.setFormatter(formatter)
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


def run_study(cfg: StudyConfig) -> int:
    preset = resolve_preset(cfg)
    output_dir = cfg.output_dir.absolute()
    specs = plan_study(preset, output_dir, cfg.long_pair, cfg.lerobot_diffusion)
    check_requests(specs, output_dir)
    if cfg.dry_run:
        print(format_plan(specs, output_dir))
        return 0
    _setup_logging(output_dir)
    logger.info("pacdp-study preset=%s output_dir=%s: %d runs", preset.name, output_dir, len(specs))
    write_json_atomic(output_dir / ("plan_long.json" if cfg.long_pair else "plan.json"),
                      {"preset": preset.name, "runs": [dataclasses.asdict(s) | {"name": s.name} for s in specs]})  # fmt: skip
    failed = []
    if cfg.train:
        for task in preset.tasks:
            prepare_dataset(task, output_dir)
        for spec in specs:
            task = preset.task(spec.task)
            config = train_config(spec, task, dataset_root(task, output_dir), preset.seed_offset, output_dir)
            write_json_atomic(spec.run_dir(output_dir) / REQUEST_FILE, config)
        chunk = cfg.max_chunk_steps if cfg.max_chunk_steps is not None else (
            preset.long_pair_chunk_steps if cfg.long_pair else None)  # fmt: skip
        if chunk is not None and chunk < 1:
            raise StudyError(f"max_chunk_steps must be >= 1, got {chunk}.")
        trainer = shlex.split(cfg.trainer) if cfg.trainer else default_trainer()
        outcome = Executor(preset, output_dir, trainer, chunk).run(specs)
        failed = outcome["failed"]
        logger.info("training: %d done, %d paused (rerun to continue), %d failed",
                    len(outcome["done"]), len(outcome["paused"]), len(failed))  # fmt: skip
    if cfg.metrics:
        from lerobot_pacdp.study.tables import report

        report(preset, specs, output_dir, long_pair=cfg.long_pair, perf=cfg.perf, unfinished=cfg.report_unfinished)
    return 1 if failed else 0


def main(argv: Sequence[str] | None = None) -> int:
    from lerobot_pacdp.metrics.checkpoints import MetricsError

    cfg = draccus.parse(config_class=StudyConfig, args=argv)
    try:
        return run_study(cfg)
    except (StudyError, MetricsError) as exc:
        print(f"pacdp-study: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
