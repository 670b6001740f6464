"""lerobot-train stops with one line (exit 2, no checkpoint) on what this plugin refuses during training."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from pacdp_testing import make_tiny_dataset

BIN = Path(sys.executable).parent
TINY = [
    "--policy.type=pacdp", "--policy.down_dims=[16,32]", "--policy.diffusion_step_embed_dim=16", "--policy.horizon=8",
    "--policy.n_action_steps=4", "--policy.drop_n_last_frames=3", "--policy.device=cpu", "--policy.push_to_hub=false",
    "--wandb.enable=false", "--num_workers=0", "--batch_size=4", "--steps=4", "--save_freq=2",
]


def _train(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.run([str(BIN / "lerobot-train"), *args], capture_output=True, text=True, timeout=600, env=env)


def _one_line_error(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, result.stderr[-3000:]
    errors = [line for line in result.stderr.splitlines() if line.startswith("lerobot-train: error:")]
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    return errors[0]


def _write_dataset(root: Path, repo_id: str, with_env_state: bool, nan_action_at: int | None = None) -> None:
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
    }
    if with_env_state:
        features["observation.environment_state"] = {"dtype": "float32", "shape": (4,), "names": None}
    dataset = LeRobotDataset.create(repo_id, fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for episode in range(2):
        for frame in range(12):
            values = {key: rng.normal(size=spec["shape"]).astype(np.float32) for key, spec in features.items()}
            if episode == 0 and frame == nan_action_at:
                values["action"][0] = np.nan  # a corrupt recording
            dataset.add_frame({**values, "task": "t"})
        dataset.save_episode()
    dataset.finalize()


@pytest.mark.slow
def test_a_nan_in_the_actions_stops_training_at_its_first_step_without_a_checkpoint(tmp_path):
    _write_dataset(tmp_path / "data", "local/nan", with_env_state=True, nan_action_at=3)
    result = _train(*TINY, "--dataset.repo_id=local/nan", f"--dataset.root={tmp_path / 'data'}",
                    f"--output_dir={tmp_path / 'out'}")
    line = _one_line_error(result)
    assert "non-finite loss at training step 1" in line and "denoise_loss = nan" in line
    assert not (tmp_path / "out" / "checkpoints").exists()


@pytest.mark.slow
def test_a_dataset_without_environment_state_or_cameras_is_named_before_the_policy_is_built(tmp_path):
    _write_dataset(tmp_path / "state_only", "local/state_only", with_env_state=False)
    result = _train(*TINY, "--dataset.repo_id=local/state_only", f"--dataset.root={tmp_path / 'state_only'}",
                    f"--output_dir={tmp_path / 'out'}")
    assert "neither `observation.environment_state` nor a camera" in _one_line_error(result)


@pytest.mark.slow
def test_fine_tuning_with_an_invalid_pacdp_value_prints_the_field_in_one_line(tmp_path):
    data = tmp_path / "data"
    make_tiny_dataset(data, episode_lengths=[20, 20])
    out = tmp_path / "out"
    assert _train(*TINY, "--dataset.repo_id=local/tiny", f"--dataset.root={data}", f"--output_dir={out}").returncode == 0
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    result = _train(f"--policy.path={checkpoint}", "--policy.kl_weight=-1", "--policy.push_to_hub=false",
                    "--dataset.repo_id=local/tiny", f"--dataset.root={data}", f"--output_dir={tmp_path / 'tuned'}")
    assert "`kl_weight` (lambda) must be a finite number >= 0, got -1.0" in _one_line_error(result)
