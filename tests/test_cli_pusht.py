"""PushT end to end through LeRobot's own commands: convert, train, checkpoint, resume, evaluate."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

BIN = Path(sys.executable).parent
TINY_POLICY = [
    "--policy.type=pacdp",
    "--policy.down_dims=[16,32]",
    "--policy.diffusion_step_embed_dim=16",
    "--policy.horizon=8",
    "--policy.n_action_steps=4",
    "--policy.drop_n_last_frames=3",
    "--policy.device=cpu",
    "--policy.push_to_hub=false",
]


def _run(args: list[str], timeout: int = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "2"}
    result = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env)
    assert result.returncode == 0, f"{args[0]} failed:\n{result.stdout[-2000:]}\n{result.stderr[-4000:]}"
    return result


@pytest.mark.slow
def test_convert_train_resume_and_evaluate_pusht(tmp_path, pusht_zarr):
    data = tmp_path / "pusht"
    _run([str(BIN / "pacdp-convert-pusht"), "--zarr", str(pusht_zarr), "--output-root", str(data), "--episodes", "0-3"])

    out = tmp_path / "train"
    common = ["--dataset.repo_id=local/pusht", f"--dataset.root={data}", "--wandb.enable=false", "--num_workers=0"]
    train = _run(
        [str(BIN / "lerobot-train"), *TINY_POLICY, *common, "--dataset.eval_split=0.25", "--eval_steps=4",
         "--steps=4", "--batch_size=8", "--save_freq=4", "--log_freq=2", f"--output_dir={out}"]
    )
    log = train.stdout + train.stderr
    frames = json.loads((data / "meta" / "info.json").read_text())["total_frames"]
    checkpoint = out / "checkpoints" / "000004" / "pretrained_model"
    n_train = json.loads((checkpoint / "config.json").read_text())["num_train_samples"]
    assert 0 < n_train < frames  # one of the 4 demos is held out
    assert f"N = {n_train} (3 episodes; training windows" in log
    assert "serving the state-only dataset from memory" in log
    assert "eval_loss=" in log and "kl:" in log and "bound_sqrt_term:" in log

    _run([str(BIN / "lerobot-train"), f"--config_path={checkpoint / 'train_config.json'}", "--resume=true", "--steps=6",
          "--save_freq=2"])
    resumed = out / "checkpoints" / "000006" / "pretrained_model"
    assert json.loads((resumed / "config.json").read_text())["num_train_samples"] == n_train
    before, after = load_file(checkpoint / "model.safetensors"), load_file(resumed / "model.safetensors")
    priors = [k for k in before if k.endswith(("_prior_mu", "prior_rho"))]
    assert priors and all(torch.equal(before[k], after[k]) for k in priors)  # same prior after resume
    assert not torch.equal(before["diffusion.unet.final_conv.1.weight"], after["diffusion.unet.final_conv.1.weight"])
    assert json.loads((out / "checkpoints" / "000006" / "training_state" / "training_step.json").read_text())["step"] == 6

    eval_dir = tmp_path / "eval"
    _run([str(BIN / "lerobot-eval"), f"--policy.path={resumed}", "--env.type=pusht",
          "--env.obs_type=environment_state_agent_pos", "--eval.n_episodes=1", "--eval.batch_size=1",
          "--eval.use_async_envs=false", "--policy.device=cpu", f"--output_dir={eval_dir}"])
    info = json.loads((eval_dir / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 1 and 0.0 <= overall["pc_success"] <= 100.0

    # The Python example loads the same checkpoint and queries actions in both inference modes.
    example = Path(__file__).parents[1] / "examples" / "query_actions.py"
    query = _run([sys.executable, str(example), "--checkpoint", str(resumed)])
    assert "mean mode: chunk shape (1, 4, 2)" in query.stdout and "two calls identical" in query.stdout
    assert "sample mode: chunk shape (1, 4, 2)" in query.stdout and "differ" in query.stdout
