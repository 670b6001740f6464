"""End to end through LeRobot's own CLIs: scripted demos -> converter -> lerobot-train -> lerobot-eval."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent
CONFIG = Path(__file__).parents[2] / "configs" / "robomimic" / "lift_cpu.json"


def _run(args, cwd):
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    result = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result


@pytest.mark.slow
def test_train_and_evaluate_on_scripted_lift_demos(tmp_path, scripted_lift_dataset):
    train_dir = tmp_path / "train"
    _run(
        [
            str(BIN / "lerobot-train"),
            f"--config_path={CONFIG}",
            "--dataset.repo_id=local/robomimic_lift",
            f"--dataset.root={scripted_lift_dataset}",
            "--steps=2", "--batch_size=4", "--save_freq=2", "--log_freq=1", "--eval_steps=0",
            "--policy.down_dims=[16,32]", "--policy.diffusion_step_embed_dim=16",
            f"--output_dir={train_dir}",
        ],
        tmp_path,
    )
    model = train_dir / "checkpoints" / "last" / "pretrained_model"
    train_config = json.loads((model / "train_config.json").read_text())
    assert train_config["env"]["type"] == "robomimic" and train_config["env"]["task"] == "lift"

    eval_dir = tmp_path / "eval"
    _run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={model}",
            "--policy.device=cpu",
            "--env.type=robomimic", "--env.task=lift", "--env.episode_length=6",
            "--eval.n_episodes=2", "--eval.batch_size=2", "--eval.use_async_envs=false",
            f"--output_dir={eval_dir}",
        ],
        tmp_path,
    )
    info = json.loads((eval_dir / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2 and 0.0 <= info["overall"]["pc_success"] <= 100.0
