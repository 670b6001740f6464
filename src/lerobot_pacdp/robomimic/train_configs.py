"""The `lerobot-train --config_path` files in `configs/robomimic/`, generated from the task table.

- `<task>.json`: the paper's setting: PAC-DP with lambda per task (1e-5 Lift/Can/ToolHang, 1e-6
  Square/Transport), rho = -4.5, 250k steps (500k for Transport/ToolHang), on the 200 `ph` demos split
  140 train / 60 held out (`episodes=[0..199]`, `eval_split=0.3`), evaluated with
  `--env.robosuite_compat=1.4` (the released files were recorded with robosuite <= 1.4).
- `<task>_cpu.json` (Lift, Can, Square): the CPU recipe for scripted demos (robosuite 1.5 data,
  `robosuite_compat=1.5`): a small U-Net (down_dims 32/64/128), batch 64, 100 warm-up steps and a cosine
  decay, with each task's rate and budget in `CPU_RECIPES` (DP's lr 1e-4 with 500 warm-up steps is sized
  for 10^5-10^6 steps and leaves PAC-DP far from converged at these budgets).

Regenerate after changing the task table: `python -m lerobot_pacdp.robomimic.train_configs` (into the
package's `configs/robomimic`, which the checkout's `configs/` links to; `--output_dir=DIR` elsewhere). A
test checks the files agree with the table.
"""

import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.cli_errors import run_draccus_cli
from lerobot_pacdp.config_files import CONFIGS_DIR
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.tasks import PAPER_EVAL_FRACTION, PAPER_NUM_DEMOS, TASKS, get_task

# rho and delta: PacdpConfig's defaults are the paper's (its single source).
PAPER_PRIOR_RHO = PacdpConfig.__dataclass_fields__["prior_rho"].default
PAPER_DELTA = PacdpConfig.__dataclass_fields__["delta"].default


@dataclass(frozen=True)
class CpuRecipe:
    """The peak learning rate, training steps and checkpoint interval of a `<task>_cpu.json`."""

    optimizer_lr: float
    steps: int
    save_freq: int


# Chosen from measured curves: Lift from results/recipes/lift (PAC-DP's learning-rate sweep; it wants a
# higher rate than DP), Can from results/recipes/can (3000-6000 steps leave it at 0.1-0.5 success; at lr 3e-3
# DP plateaus by 15000 steps, PAC-DP still climbs at 20000). Square takes Lift's recipe, not measured.
_LIFT_RECIPE = CpuRecipe(optimizer_lr=6e-3, steps=3000, save_freq=500)
CPU_RECIPES = {
    "lift": _LIFT_RECIPE,
    "can": CpuRecipe(optimizer_lr=3e-3, steps=20_000, save_freq=2500),
    "square": _LIFT_RECIPE,
}
CPU_TASKS = tuple(CPU_RECIPES)  # the tasks with scripted experts


def dataset_repo_id(task: str, scripted: bool = False) -> str:
    return f"local/robomimic_{get_task(task).name}{'_scripted' if scripted else ''}"


def paper_config(task: str) -> dict:
    t = get_task(task)
    return {
        "dataset": {
            "repo_id": dataset_repo_id(t.name),
            "episodes": list(range(PAPER_NUM_DEMOS)),
            "eval_split": PAPER_EVAL_FRACTION,
        },
        "env": {"type": "robomimic", "task": t.name, "robosuite_compat": compat.LEGACY},
        "policy": {
            "type": "pacdp",
            "kl_weight": t.kl_weight,
            "prior_rho": PAPER_PRIOR_RHO,
            "delta": PAPER_DELTA,
            "inference_mode": "mean",
            # Chi et al.'s code, which the paper builds on, trains on copy-padded actions too.
            "do_mask_loss_for_padding": False,
            "push_to_hub": False,
        },
        "steps": t.train_steps,
        "batch_size": 256,
        "save_freq": 5000,
        "eval_steps": 5000,
        "env_eval_freq": 0,
        "log_freq": 200,
        "seed": 1000,
        "num_workers": 4,
    }


def cpu_config(task: str) -> dict:
    t, recipe = get_task(task), CPU_RECIPES[task]
    return {
        "dataset": {"repo_id": dataset_repo_id(t.name, scripted=True), "eval_split": 0.1},
        "env": {"type": "robomimic", "task": t.name, "robosuite_compat": compat.NATIVE},
        "policy": {
            "type": "pacdp",
            "kl_weight": t.kl_weight,
            "prior_rho": PAPER_PRIOR_RHO,
            "delta": PAPER_DELTA,
            "down_dims": [32, 64, 128],
            "diffusion_step_embed_dim": 64,
            "optimizer_lr": recipe.optimizer_lr,
            "scheduler_warmup_steps": 100,
            "device": "cpu",
            "push_to_hub": False,
        },
        "steps": recipe.steps,
        "batch_size": 64,
        "save_freq": recipe.save_freq,
        "eval_steps": recipe.save_freq,
        "env_eval_freq": 0,
        "log_freq": 100,
        "seed": 1000,
        "num_workers": 0,
    }


def expected_files() -> dict[str, dict]:
    """{file name: content} of every config file in configs/robomimic/."""
    files = {f"{name}.json": paper_config(name) for name in TASKS}
    files.update({f"{name}_cpu.json": cpu_config(name) for name in CPU_TASKS})
    return files


def render(content: dict) -> str:
    """JSON text of a config file (episode lists on one line, like configs/pusht/)."""
    text = json.dumps(content, indent=2)
    if "episodes" in content.get("dataset", {}):
        one_line = json.dumps(content["dataset"]["episodes"])
        text = text.replace(json.dumps(content["dataset"]["episodes"], indent=2).replace("\n", "\n    "), one_line)
    return text + "\n"


def write_all(directory: str | Path) -> list[Path]:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, content in expected_files().items():
        path = directory / name
        write_text_atomic(path, render(content))
        written.append(path)
    return written


@dataclass
class TrainConfigsConfig:
    output_dir: Path = CONFIGS_DIR / "robomimic"  # where the config files are written


def _write_and_list(cfg: TrainConfigsConfig) -> int:
    for written in write_all(cfg.output_dir):
        print(written)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_draccus_cli("python -m lerobot_pacdp.robomimic.train_configs", TrainConfigsConfig, _write_and_list, argv)


if __name__ == "__main__":
    sys.exit(main())
