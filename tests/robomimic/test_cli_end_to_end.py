"""End to end through LeRobot's own CLIs: scripted demos -> converter -> lerobot-train -> lerobot-eval."""

import json
import os
import subprocess
import sys
import time
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

    # The main job's last stage: lerobot-eval, pacdp-metrics (held-out NPE), pacdp-summarize-run.
    script = Path(__file__).parents[2] / "examples" / "evaluate_and_summarize.sh"
    env_flags = ["--env.type=robomimic", "--env.task=lift", "--env.episode_length=6", "--policy.device=cpu"]
    started = int(time.time()) - 100  # the job started 100 s before its evaluation (epoch seconds)
    result = subprocess.run(
        ["bash", str(script), str(model), str(tmp_path), "lift", str(started), "--", *env_flags],
        env={**os.environ, "HF_HUB_OFFLINE": "1", "EVAL_EPISODES": "3", "EVAL_BATCH": "3", "PATH": f"{BIN}:{os.environ['PATH']}"},
        capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    # Two lerobot-eval processes (EVAL_PROCS default 2) on consecutive seed ranges: 2 episodes, then 1.
    infos = [json.loads((tmp_path / "eval" / f"part{k}" / "eval_info.json").read_text()) for k in (0, 1)]
    assert [info["overall"]["n_episodes"] for info in infos] == [2, 1]
    assert "'seed': 1000," in result.stdout + result.stderr  # lerobot-eval logs its config
    assert "'seed': 1002," in (tmp_path / "eval" / "part1.log").read_text()
    summary = json.loads((tmp_path / "summary.json").read_text())
    successes = sum(bool(s) for info in infos for task in info["per_task"] for s in task["metrics"]["successes"])
    assert summary["task"] == "lift" and summary["n_episodes"] == 3 and summary["train_steps"] == 2
    assert summary["success_rate"] == successes / 3 and summary["successes"] == successes
    low, high = summary["ci95"]
    assert 0.0 <= low <= summary["success_rate"] <= high <= 1.0
    assert summary["policy"].startswith("pacdp PAC-DP (kl_weight=1e-05") and summary["heldout_npe"] > 0
    assert 100 <= summary["wall_time_s"] <= 100 + 900 and "success rate:" in result.stdout
