"""The runs of a study: tasks x demos x seeds x methods, their episodes and their lerobot-train configs.

For each seed one held-out set of demos is drawn, disjoint from every training set of that seed; the
training demos of (demos, seed) are the first `demos` of the remaining ones in a seeded order, so they are
identical for every method and nested (the 20 are among the 40). Each run has its own directory,
`<output_dir>/runs/<task>/<group>/<name>/`, with lerobot-train's output dir `train/` inside.
"""

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import draccus
import numpy as np

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.study.presets import Preset, StudyError, TaskPreset

# DP is pacdp's `bayesian=false` twin (PAC-DP minus what the paper changes); LeRobot-DP, LeRobot's own
# `diffusion` policy with the same settings, is an extra (`--lerobot_diffusion=true`).
Method = Literal["DP", "BDP", "PAC-DP", "LeRobot-DP"]
Group = Literal["main", "long"]  # the study, or its long runs (`--long_pair=true`)
SPLIT_SALT = 20_260_523  # decorrelates the episode order from the training seed


@dataclass(frozen=True)
class RunSpec:
    """One lerobot-train run of the study."""

    task: str
    demos: int
    seed: int
    method: Method
    kl_weight: float | None  # None for DP and LeRobot-DP
    prior_rho: float | None  # None for DP and LeRobot-DP
    steps: int
    save_freq: int
    train_episodes: tuple[int, ...]
    heldout_episodes: tuple[int, ...]
    group: Group = "main"

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
        """The run's lerobot-train `--output_dir`."""
        return self.run_dir(output_dir) / "train"


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
    points: list[tuple[Method, float | None, float | None]]
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


def plan_study(
    preset: Preset, num_episodes: Mapping[str, int], long_pair: bool = False, lerobot_diffusion: bool = False
) -> list[RunSpec]:
    """Every run of the preset, given the number of demos in each task's dataset."""
    return [
        spec
        for task in preset.tasks
        for spec in plan_task(task, preset, num_episodes[task.name], long_pair, lerobot_diffusion)
    ]


def keep_methods(specs: list[RunSpec], methods: Sequence[str] | None) -> list[RunSpec]:
    """The runs of the given methods (all when None): e.g. only PAC-DP at a longer budget, to see where its
    success plateaus."""
    if methods is None:
        return specs
    unknown = sorted(set(methods) - set(get_args(Method)))
    if unknown:
        raise StudyError(f"--methods: unknown {', '.join(unknown)}; choose from {', '.join(get_args(Method))}.")
    return [spec for spec in specs if spec.method in methods]


def lerobot_diffusion_policy(pacdp_policy: Mapping) -> dict:
    """LeRobot `diffusion` settings of a `pacdp` policy's config dict (`PacdpConfig.diffusion_twin`: the same
    U-Net, schedule, inference and normalisation, no PAC-Bayes fields), written as the fields the dict sets
    and those where the twin differs from DiffusionConfig's defaults."""
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    pacdp = draccus.decode(PacdpConfig, {k: v for k, v in pacdp_policy.items() if k != "type"})
    twin, defaults = draccus.encode(pacdp.diffusion_twin()), draccus.encode(DiffusionConfig())
    kept = {k: v for k, v in twin.items() if k != "type" and (k in pacdp_policy or v != defaults.get(k))}
    return {"type": "diffusion"} | kept


def train_config(spec: RunSpec, task: TaskPreset, dataset_root: Path | None, seed_offset: int, output_dir: Path) -> dict:
    """The complete lerobot-train config of one run (written to its run dir as `train_request.json`)."""
    config = copy.deepcopy(task.train_config)
    config["dataset"].update(episodes=list(spec.train_episodes), eval_split=0.0)
    if dataset_root is not None:
        config["dataset"]["root"] = str(dataset_root)
    policy = config["policy"]
    if spec.method == "LeRobot-DP":
        config["policy"] = lerobot_diffusion_policy(policy)
    elif spec.method == "DP":
        policy.update(type="pacdp", bayesian=False)
    else:
        policy.update(type="pacdp", kl_weight=spec.kl_weight, prior_rho=spec.prior_rho)
    # The held-out demos are evaluated by the metrics sweep, not by lerobot-train's eval split.
    config.update(steps=spec.steps, save_freq=spec.save_freq, seed=seed_offset + spec.seed, eval_steps=0,
                  env_eval_freq=0, output_dir=str(spec.train_dir(output_dir)), wandb={"enable": False})  # fmt: skip
    return config
