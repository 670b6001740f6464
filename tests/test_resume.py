"""`lerobot-train --resume=true` continues a pacdp run exactly: the resumed run equals an uninterrupted one."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from pacdp_testing import make_tiny_dataset

BIN = Path(sys.executable).parent
TINY = [
    "--policy.type=pacdp", "--policy.down_dims=[16,32]", "--policy.diffusion_step_embed_dim=16", "--policy.horizon=8",
    "--policy.n_action_steps=4", "--policy.drop_n_last_frames=3", "--policy.device=cpu", "--policy.push_to_hub=false",
    "--dataset.repo_id=local/tiny", "--wandb.enable=false", "--num_workers=0", "--batch_size=8",
    "--dataset.eval_split=0.34", "--eval_steps=3",
]


def _train(*args: str) -> None:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    result = subprocess.run([str(BIN / "lerobot-train"), *args], capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-4000:]


@pytest.mark.slow
def test_a_resumed_run_equals_an_uninterrupted_one_bitwise(tmp_path):
    data = tmp_path / "data"
    make_tiny_dataset(data, episode_lengths=[30, 25, 40])  # 1 training episode: 27 windows, 4 batches an epoch
    common = [*TINY, f"--dataset.root={data}", "--save_freq=7"]
    _train(*common, "--steps=14", f"--output_dir={tmp_path / 'full'}")
    _train(*common, "--steps=7", f"--output_dir={tmp_path / 'part'}")
    # Step 7 is mid-epoch and the run has evaluated the held-out loss since the last epoch boundary.
    resume_from = tmp_path / "part" / "checkpoints" / "000007" / "pretrained_model" / "train_config.json"
    _train(f"--config_path={resume_from}", "--resume=true", "--steps=14")

    for step in ("000007", "000014"):
        full = load_file(tmp_path / "full" / "checkpoints" / step / "pretrained_model" / "model.safetensors")
        resumed = load_file(tmp_path / "part" / "checkpoints" / step / "pretrained_model" / "model.safetensors")
        assert full.keys() == resumed.keys()
        assert any(k.startswith("raw_diffusion.") for k in full) and full["num_updates"].item() == int(step)
        different = [k for k in full if not torch.equal(full[k], resumed[k])]
        assert different == [], f"step {step}: {len(different)} tensors differ, e.g. {different[:3]}"
