"""`pacdp-study`: the DP vs BDP vs PAC-DP reproduction study (paper Sec. IV), resumable, in one command.

    pacdp-study --preset=cpu --output_dir=outputs/study_cpu            # local lerobot-train subprocesses
    pacdp-study --preset=cpu --output_dir=outputs/study_cpu --dry_run=true
    pacdp-study --preset=cpu --output_dir=outputs/study_long --long_pair=true --jobs=3  # 6k more steps per call
    pacdp-study --preset=paper --output_dir=/scratch/study_paper --executor=slurm --slurm.partition=gpu

Plans the runs (`study.plan`), trains the unfinished ones where `--executor` says (`study.executors`,
`study.slurm`), then computes the metrics (`study.evaluation`) and writes the tables (`study.tables`).
`run_study(StudyConfig(...))` is the same from Python.
"""

import dataclasses
import logging
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_pacdp.cli_errors import run_draccus_cli
from lerobot_pacdp.study.data import count_episodes, dataset_fingerprint, dataset_root, prepare_dataset
from lerobot_pacdp.study.evaluation import adopt_published, evaluate_runs
from lerobot_pacdp.study.executors import LocalExecutor, Outcome, default_trainer
from lerobot_pacdp.study.plan import RunSpec, keep_methods, plan_study, train_config
from lerobot_pacdp.study.presets import Preset, StudyError, get_preset, long_pair_preset, with_overrides
from lerobot_pacdp.study.slurm import SlurmExecutor, SlurmOptions
from lerobot_pacdp.study.state import (
    REQUEST_FILE,
    check_datasets,
    check_requests,
    format_plan,
    write_json_atomic,
)
from lerobot_pacdp.study.tables import report

logger = logging.getLogger("pacdp-study")

EXECUTORS = ("local", "slurm")


@dataclass
class StudyConfig:
    """`pacdp-study` options (`--flag=value`; lists as `--seeds=[0,1]`). Unset overrides keep the preset's."""

    preset: str = "cpu"  # cpu | paper (see lerobot_pacdp.study.presets)
    output_dir: Path = Path("outputs/study")
    # PushT demos (Diffusion Policy's pusht_cchi_v7_replay.zarr, from its pusht.zip), converted into output_dir
    # once; needed to plan a PushT task until its dataset is there.
    pusht_zarr: Path | None = None
    dry_run: bool = False  # print the plan (runs, episodes, what is done / to resume; SLURM: each job) and exit
    long_pair: bool = False  # instead of the study: the long DP / BDP / PAC-DP runs (reference point, first seed)
    lerobot_diffusion: bool = False  # also train LeRobot's own `diffusion` policy (method LeRobot-DP) beside DP
    tasks: list[str] | None = None
    demos: list[int] | None = None
    seeds: list[int] | None = None
    steps: int | None = None
    save_freq: int | None = None  # default with --steps: steps / 10
    methods: list[str] | None = None  # train and report only these (DP, BDP, PAC-DP, LeRobot-DP); default: all
    kl_weights: list[float] | None = None  # PAC-DP grid (each task's reference lambda always included)
    prior_rhos: list[float] | None = None  # BDP / PAC-DP rho grid
    executor: str = "local"  # local: lerobot-train subprocesses here; slurm: one job per run (--slurm.*)
    jobs: int | None = None  # local: lerobot-train runs side by side (CPU threads are split between them)
    max_chunk_steps: int | None = None  # local: stop each run after this many more steps (rerun to continue)
    slurm: SlurmOptions = field(default_factory=SlurmOptions)
    train: bool = True  # false: only (re)compute metrics and tables of finished runs
    metrics: bool = True  # false: train only
    report_unfinished: bool = False  # also report runs stopped before their last step, up to their last checkpoint
    # a published study's metrics/ (e.g. results/study_cpu_v2/metrics): its runs' rows and success rates join
    # the tables where output_dir has none of their own (seeds trained in other checkouts)
    published_metrics: Path | None = None
    success_episodes: int | None = None  # rollouts per evaluated checkpoint (0: no success rate)
    success_every: int | None = None  # also roll out checkpoints at multiples of this step (0: final only)
    perf: bool = False  # also (re)measure the performance table (lerobot_pacdp.speed_benchmark)
    trainer: str | None = None  # command replacing lerobot-train (for tests); its args are the same


def resolve_preset(cfg: StudyConfig) -> Preset:
    preset = get_preset(cfg.preset)
    if cfg.long_pair:
        preset = long_pair_preset(preset)
    return with_overrides(
        preset, tasks=cfg.tasks, demos=cfg.demos, seeds=cfg.seeds, steps=cfg.steps, save_freq=cfg.save_freq,
        kl_weights=cfg.kl_weights, prior_rhos=cfg.prior_rhos, jobs=cfg.jobs, success_episodes=cfg.success_episodes,
        success_every=cfg.success_every,
    )  # fmt: skip


def _setup_logging(output_dir: Path) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    formatter = logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S")
    for handler in (logging.StreamHandler(sys.stdout), logging.FileHandler(output_dir / "study.log")):
        handler.setFormatter(formatter)
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


def _executor(cfg: StudyConfig, preset: Preset, output_dir: Path) -> LocalExecutor | SlurmExecutor:
    if cfg.executor not in EXECUTORS:
        raise StudyError(f"--executor must be one of {', '.join(EXECUTORS)}, got {cfg.executor!r}.")
    trainer = shlex.split(cfg.trainer) if cfg.trainer else default_trainer()
    if cfg.executor == "slurm":
        if cfg.max_chunk_steps is not None:
            raise StudyError("--max_chunk_steps is for --executor=local; on SLURM a run that reaches "
                             "--slurm.timeout_min is requeued and resumes.")  # fmt: skip
        return SlurmExecutor(output_dir, trainer, cfg.slurm)
    chunk = cfg.max_chunk_steps if cfg.max_chunk_steps is not None else (
        preset.long_pair_chunk_steps if cfg.long_pair else None)  # fmt: skip
    if chunk is not None and chunk < 1:
        raise StudyError(f"max_chunk_steps must be >= 1, got {chunk}.")
    return LocalExecutor(output_dir, trainer, preset.jobs, chunk)


def _write_requests(specs: list[RunSpec], preset: Preset, output_dir: Path) -> None:
    for spec in specs:
        task = preset.task(spec.task)
        config = train_config(spec, task, dataset_root(task, output_dir), preset.seed_offset, output_dir)
        write_json_atomic(spec.run_dir(output_dir) / REQUEST_FILE, config)


def run_study(cfg: StudyConfig) -> int:
    """Plan, train (unless `train` is false), then metrics and tables (unless `metrics` is false); 1 if a run failed."""
    preset = resolve_preset(cfg)
    output_dir = cfg.output_dir.absolute()
    pusht_zarr = cfg.pusht_zarr.absolute() if cfg.pusht_zarr is not None else None
    episodes = {task.name: count_episodes(task, output_dir, pusht_zarr) for task in preset.tasks}
    specs = keep_methods(plan_study(preset, episodes, cfg.long_pair, cfg.lerobot_diffusion), cfg.methods)
    check_requests(specs, output_dir)
    executor = _executor(cfg, preset, output_dir) if cfg.train or cfg.dry_run else None
    if cfg.dry_run:
        print(format_plan(specs, output_dir))
        if isinstance(executor, SlurmExecutor) and cfg.train:
            print(executor.preview(specs))
        return 0
    _setup_logging(output_dir)
    logger.info("pacdp-study preset=%s output_dir=%s: %d runs", preset.name, output_dir, len(specs))
    write_json_atomic(output_dir / ("plan_long.json" if cfg.long_pair else "plan.json"),
                      {"preset": preset.name, "runs": [dataclasses.asdict(s) | {"name": s.name} for s in specs]})  # fmt: skip
    outcome = Outcome()
    if executor is not None:
        for task in preset.tasks:
            prepare_dataset(task, output_dir, pusht_zarr)
    fingerprints = {task.name: dataset_fingerprint(task, output_dir) for task in preset.tasks}
    check_datasets(specs, output_dir, fingerprints, record=executor is not None)
    if executor is not None:
        _write_requests(specs, preset, output_dir)
        outcome = executor.run(specs)
        logger.info("training: %d done, %d paused (rerun to continue), %d failed, %d submitted",
                    len(outcome.done), len(outcome.paused), len(outcome.failed), len(outcome.submitted))  # fmt: skip
    if outcome.submitted:
        logger.info("the submitted runs train on the cluster. Where they stand: the same command with "
                    "--dry_run=true; their metrics and tables once they are done (on a GPU node): the same "
                    "command with --train=false (--report_unfinished=true for those still running).")  # fmt: skip
    elif cfg.metrics:
        if cfg.published_metrics is not None:
            adopt_published(cfg.published_metrics, output_dir)
        rows = evaluate_runs(preset, specs, output_dir, cfg.report_unfinished, fingerprints)
        report(preset, specs, rows, output_dir, long_pair=cfg.long_pair, perf=cfg.perf)
    return 1 if outcome.failed else 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("pacdp-study", StudyConfig, run_study, argv)


if __name__ == "__main__":
    sys.exit(main())
