"""The study presets: every number a study uses is set here once (or read from the file that owns it).

- `cpu`: PushT from Diffusion Policy's real demos (`--pusht_zarr`), configs/pusht/pacdp_cpu.json with the
  U-Net and lambda the committed results/study_cpu_pusht* ran with (down_dims 64/128/256, step embedding
  64, the U-Net of the `cpu` speed benchmark; lambda 1e-4), 20 and 40 training demos, 20 held-out demos
  per seed, DP / BDP / PAC-DP, seeds 0 and 1, 1200 steps at batch 64, a checkpoint every 120 steps, two
  runs side by side. The learning rate is raised to 1e-3 with a 50-step warm-up (the diffusion preset's
  1e-4 / 500 steps is sized for 10^5-10^6 steps) so 1200 steps fit the data well and DP can overfit within
  the run. `long_pair=true` instead trains DP, BDP and PAC-DP on 20 demos for 20k steps at batch 16 (~130
  epochs of the 20 demos), in chunks of `long_pair_chunk_steps`, resumable across sessions.
- `paper`: paper Sec. IV on GPUs: PushT (configs/pusht/pacdp_paper.json: 10^6 steps, batch 256, paper
  U-Net) and the five robomimic tasks (`robomimic.train_configs.paper_config`, steps and lambda from
  `robomimic.tasks.TASKS`), the paper's held-out demos per seed and low-data training-demo counts
  (`robomimic.tasks`; Transport and ToolHang only at the largest), seeds 0-2, the paper's grid lambda in
  {1e-5, 1e-6} (plus each task's own lambda) x rho in {-3.5, -4, -4.5, -5}.

Measured run times are in the README (Reproduction study, Results), not here.
"""

import copy
from dataclasses import dataclass, replace

from lerobot_pacdp.cli_errors import UserInputError
from lerobot_pacdp.config_files import load_config_file
from lerobot_pacdp.robomimic.tasks import LOW_DATA_TRAINING_DEMOS, PAPER_HELDOUT_DEMOS, PAPER_NUM_DEMOS, TASKS
from lerobot_pacdp.robomimic.train_configs import PAPER_PRIOR_RHO, paper_config

PAPER_KL_GRID = (1e-5, 1e-6)  # Sec. IV-B "Hyperparameter Sensitivity Analysis"
PAPER_RHO_GRID = (-3.5, -4.0, -4.5, -5.0)
PAPER_SEEDS = (0, 1, 2)


class StudyError(UserInputError):
    """A problem with a study's settings or inputs; the CLI prints it and exits 2."""


@dataclass(frozen=True)
class ScriptedDemos:
    """Demos a study records itself with `pacdp-scripted-demos` (the same file for every method and seed)."""

    num_demos: int
    seed: int = 0
    action_noise: float = 0.05  # the main job's


@dataclass(frozen=True)
class TaskPreset:
    """One benchmark task of a study.

    `train_config` is the base lerobot-train config (dataset repo id, env, policy, batch, workers); the
    plan replaces the episodes, seed, steps, method and output dir per run. The dataset lives at
    `dataset_root` (relative paths are under the study's output dir; `None`: LeRobot's default location
    for the repo id). With `from_pusht_zarr` a missing dataset is converted from the PushT replay buffer
    the study is given (`--pusht_zarr`); with `scripted` it is recorded by the task's scripted expert and
    converted; otherwise it must exist.
    """

    name: str
    train_config: dict
    demos: tuple[int, ...]
    heldout: int  # held-out demos per seed, disjoint from every training set of that seed
    steps: int
    save_freq: int
    reference_kl_weight: float  # Table I / Fig. 3 PAC-DP lambda (the task's paper value)
    dataset_root: str | None = None
    from_pusht_zarr: bool = False
    num_episodes: int | None = None  # expected demos in the dataset (planning before it is converted)
    scripted: ScriptedDemos | None = None

    @property
    def repo_id(self) -> str:
        return self.train_config["dataset"]["repo_id"]


@dataclass(frozen=True)
class PerfRow:
    """One row of the performance table: a run of the speed benchmark (`lerobot_pacdp.speed_benchmark`)."""

    speed_preset: str  # the benchmark's U-Net preset
    batch_size: int
    train_steps: int | None = None  # timed training steps per policy (None: the benchmark preset's)
    latency_calls: int | None = None  # timed action chunks per policy (None: the benchmark preset's)


@dataclass(frozen=True)
class Preset:
    """A whole study: tasks x demos x seeds x methods (DP, BDP over rho, PAC-DP over lambda x rho)."""

    name: str
    tasks: tuple[TaskPreset, ...]
    seeds: tuple[int, ...]
    kl_weights: tuple[float, ...]  # PAC-DP grid (each task's reference lambda is added)
    prior_rhos: tuple[float, ...]  # BDP and PAC-DP grid
    reference_rho: float  # Table I / Fig. 3 rho
    seed_offset: int  # lerobot-train --seed = seed_offset + study seed
    jobs: int  # lerobot-train runs side by side
    # Metrics (lerobot_pacdp.metrics.sweep): per run the mean over its last `last_k` checkpoints.
    last_k: int
    nll_steps: int | None  # diffusion steps of the NLL bound (None: all)
    frame_stride: int  # every k-th held-out window
    metrics_batch_size: int
    success_episodes: int  # rollouts per evaluated checkpoint (0: no success rate)
    success_last_k: int  # success rate on each run's last k checkpoints only (rollouts are costly)
    success_every: int  # also roll out each checkpoint whose step is a multiple of this (success curves; 0: none)
    device: str | None
    perf_rows: tuple[PerfRow, ...]  # the performance table
    # The long runs (`--long_pair=true`): DP, BDP and PAC-DP at the reference point, first seed.
    long_pair_demos: int = 20
    long_pair_steps: int = 0
    long_pair_save_freq: int = 0
    long_pair_chunk_steps: int | None = None  # each invocation trains a long run this many more steps
    long_pair_batch_size: int | None = None  # None: the task's own batch size

    def task(self, name: str) -> TaskPreset:
        for task in self.tasks:
            if task.name == name:
                return task
        raise StudyError(f"preset {self.name!r} has no task {name!r}; choose from {[t.name for t in self.tasks]}.")


def _cpu_preset() -> Preset:
    base = load_config_file("pusht/pacdp_cpu.json")
    # The U-Net and lambda results/study_cpu_pusht* ran with (pacdp_cpu.json's before its all-demos recipe).
    base["policy"].update(down_dims=[64, 128, 256], kl_weight=1e-4, optimizer_lr=1e-3, scheduler_warmup_steps=50)
    base.update(batch_size=64, num_workers=0, log_freq=50)
    pusht = TaskPreset(
        name="pusht",
        train_config=base,
        demos=(20, 40),
        heldout=20,
        steps=1200,
        save_freq=120,
        reference_kl_weight=base["policy"]["kl_weight"],
        dataset_root="data/pusht",
        from_pusht_zarr=True,
    )
    return Preset(
        name="cpu",
        tasks=(pusht,),
        seeds=(0, 1),
        kl_weights=(),
        prior_rhos=(base["policy"]["prior_rho"],),
        reference_rho=base["policy"]["prior_rho"],
        seed_offset=base["seed"],
        jobs=2,
        last_k=3,
        nll_steps=25,
        frame_stride=2,
        metrics_batch_size=256,
        success_episodes=10,
        success_last_k=1,
        success_every=0,
        device="cpu",
        # The paper U-Net is slow on a CPU: 10 timed steps and 5 chunks each.
        perf_rows=(PerfRow("cpu", 64), PerfRow("paper", 8, train_steps=10, latency_calls=5)),
        long_pair_steps=20_000,
        long_pair_save_freq=1_000,
        long_pair_chunk_steps=6_000,
        long_pair_batch_size=16,
    )


def _cpu_v2_task(name: str, config_file: str, demos: tuple[int, ...], scripted: ScriptedDemos | None) -> TaskPreset:
    """A task of the CPU evidence study at its CPU recipe (the config file's lr, warm-up, steps, save_freq)."""
    config = load_config_file(config_file)
    config.update(batch_size=64, num_workers=0, log_freq=100)
    steps, save_freq = config.pop("steps"), config.pop("save_freq")
    return TaskPreset(
        name=name,
        train_config=config,
        demos=demos,
        heldout=20,
        steps=steps,
        save_freq=save_freq,
        reference_kl_weight=config["policy"]["kl_weight"],
        dataset_root=f"data/{name}",
        from_pusht_zarr=scripted is None,
        scripted=scripted,
    )


def _cpu_v2_preset() -> Preset:
    """Issue 14's evidence study: DP twin / BDP / PAC-DP at each task's CPU recipe, 3 seeds, 50 rollouts."""
    scripted = ScriptedDemos(num_demos=60)  # 20 held out per seed + at most 40 for training
    tasks = (
        _cpu_v2_task("lift", "robomimic/lift_cpu.json", (20, 40), scripted),
        _cpu_v2_task("can", "robomimic/can_cpu.json", (20, 40), scripted),
        _cpu_v2_task("pusht", "pusht/pacdp_cpu.json", (20,), None),
    )
    rho = tasks[0].train_config["policy"]["prior_rho"]
    return Preset(
        name="cpu_v2",
        tasks=tasks,
        seeds=PAPER_SEEDS,
        kl_weights=(),
        prior_rhos=(rho,),
        reference_rho=rho,
        seed_offset=tasks[0].train_config["seed"],
        jobs=2,
        last_k=1,  # the final checkpoint
        nll_steps=None,  # all diffusion steps: the paper-compatible NLL beside the bound
        frame_stride=2,
        metrics_batch_size=256,
        success_episodes=50,
        success_last_k=1,
        success_every=1000,
        device="cpu",
        perf_rows=(PerfRow("cpu", 64),),
    )


def _paper_task(
    name: str, config: dict, kl: float, demos: tuple[int, ...], root: str | None, from_pusht_zarr: bool = False,
    num_episodes: int | None = None,
) -> TaskPreset:
    """A task at paper scale from its lerobot-train config (steps and save_freq included)."""
    config = copy.deepcopy(config)
    config["dataset"].pop("episodes", None)  # the plan picks them per (demos, seed)
    steps, save_freq = config.pop("steps"), config.pop("save_freq")
    return TaskPreset(
        name, config, demos, PAPER_HELDOUT_DEMOS, steps, save_freq, kl, root, from_pusht_zarr, num_episodes
    )


def _paper_preset() -> Preset:
    pusht = load_config_file("pusht/pacdp_paper.json")
    tasks = [
        _paper_task("pusht", pusht, pusht["policy"]["kl_weight"], LOW_DATA_TRAINING_DEMOS, "data/pusht", True)
    ]
    for name, task in TASKS.items():
        demos = LOW_DATA_TRAINING_DEMOS if task.train_steps < 500_000 else LOW_DATA_TRAINING_DEMOS[-1:]
        tasks.append(_paper_task(name, paper_config(name), task.kl_weight, demos, None, False, PAPER_NUM_DEMOS))
    return Preset(
        name="paper",
        tasks=tuple(tasks),
        seeds=PAPER_SEEDS,
        kl_weights=PAPER_KL_GRID,
        prior_rhos=PAPER_RHO_GRID,
        reference_rho=PAPER_PRIOR_RHO,
        seed_offset=pusht["seed"],
        jobs=1,
        last_k=10,
        nll_steps=None,
        frame_stride=1,
        metrics_batch_size=1024,
        success_episodes=1000,
        success_last_k=10,
        success_every=0,
        device=None,
        perf_rows=(PerfRow("paper", 256),),
        long_pair_demos=20,
        long_pair_steps=pusht["steps"],
        long_pair_save_freq=pusht["save_freq"],
        long_pair_chunk_steps=100_000,
    )


PRESETS = {"cpu": _cpu_preset, "cpu_v2": _cpu_v2_preset, "paper": _paper_preset}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise StudyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}.")
    return PRESETS[name]()


def long_pair_preset(preset: Preset) -> Preset:
    """The preset's long runs instead of its study: its first task and seed, `long_pair_demos` training demos,
    `long_pair_steps` steps (and `long_pair_batch_size`, if set)."""
    if preset.long_pair_steps < 1:
        raise StudyError(f"preset {preset.name!r} defines no long pair.")
    batch = {} if preset.long_pair_batch_size is None else {"batch_size": preset.long_pair_batch_size}
    task = preset.tasks[0]
    task = replace(task, demos=(preset.long_pair_demos,), steps=preset.long_pair_steps,
                   save_freq=preset.long_pair_save_freq, train_config={**task.train_config, **batch})  # fmt: skip
    long_pair = replace(preset, tasks=(task,), seeds=preset.seeds[:1])
    validate(long_pair)
    return long_pair


def with_overrides(
    preset: Preset,
    *,
    tasks: list[str] | None = None,
    demos: list[int] | None = None,
    seeds: list[int] | None = None,
    steps: int | None = None,
    save_freq: int | None = None,
    kl_weights: list[float] | None = None,
    prior_rhos: list[float] | None = None,
    jobs: int | None = None,
    success_episodes: int | None = None,
    success_every: int | None = None,
) -> Preset:
    """The preset with CLI overrides applied (None keeps the preset's value), validated."""
    selected = [preset.task(name) for name in tasks] if tasks else list(preset.tasks)
    if demos is not None:
        selected = [replace(t, demos=tuple(demos)) for t in selected]
    if steps is not None:
        if save_freq is None:  # keep ~10 checkpoints per run for the curves
            save_freq = max(1, steps // 10)
        selected = [replace(t, steps=steps) for t in selected]
    if save_freq is not None:
        selected = [replace(t, save_freq=save_freq) for t in selected]
    preset = replace(
        preset,
        tasks=tuple(selected),
        seeds=tuple(seeds) if seeds is not None else preset.seeds,
        kl_weights=tuple(kl_weights) if kl_weights is not None else preset.kl_weights,
        prior_rhos=tuple(prior_rhos) if prior_rhos is not None else preset.prior_rhos,
        jobs=jobs if jobs is not None else preset.jobs,
        success_episodes=success_episodes if success_episodes is not None else preset.success_episodes,
        success_every=success_every if success_every is not None else preset.success_every,
    )
    validate(preset)
    return preset


def validate(preset: Preset) -> None:
    if not preset.seeds or len(set(preset.seeds)) != len(preset.seeds):
        raise StudyError(f"seeds must be a non-empty list of distinct integers, got {list(preset.seeds)}.")
    if not preset.prior_rhos:
        raise StudyError("prior_rhos (the BDP / PAC-DP rho grid) must not be empty.")
    if any(k <= 0 for k in preset.kl_weights):
        raise StudyError(f"PAC-DP kl_weights must be > 0 (lambda 0 is BDP), got {list(preset.kl_weights)}.")
    if preset.jobs < 1:
        raise StudyError(f"jobs must be >= 1, got {preset.jobs}.")
    if preset.success_every < 0:
        raise StudyError(f"success_every must be >= 0 (0: only the final checkpoints), got {preset.success_every}.")
    for task in preset.tasks:
        if not task.demos or any(d < 1 for d in task.demos):
            raise StudyError(f"{task.name}: demos must be positive training-demo counts, got {list(task.demos)}.")
        if task.steps < 1 or not 1 <= task.save_freq <= task.steps:
            raise StudyError(f"{task.name}: need steps >= 1 and 1 <= save_freq <= steps, got {task.steps}, {task.save_freq}.")
