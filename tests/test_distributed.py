"""Multi-process data-parallel training (gloo on CPU) with LeRobot's DDP settings."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import random_batch, tiny_config

TESTS_DIR = Path(__file__).parent


@pytest.mark.slow
def test_ddp_counts_the_kl_once_and_keeps_every_rank_identical(tmp_path):
    torchrun = Path(sys.executable).parent / "torchrun"
    env = {**os.environ, "PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [str(torchrun), "--nproc_per_node", "2", "--master_port", "29517", str(TESTS_DIR / "ddp_worker.py"), str(tmp_path)],
        capture_output=True, text=True, timeout=600, env=env,
    )
    assert result.returncode == 0, result.stderr[-4000:]

    # Every rank ends with the same mu and rho, trained and averaged (EMA).
    rank0, rank1 = (torch.load(tmp_path / f"final_rank{r}.pt") for r in (0, 1))
    assert rank0.keys() == rank1.keys()
    assert any(k.startswith("raw_diffusion.") for k in rank0) and any(k.startswith("diffusion.") for k in rank0)
    assert all(torch.equal(rank0[k], rank1[k]) for k in rank0)
    initial = torch.load(tmp_path / "initial.pt")
    assert not torch.equal(rank0["diffusion.unet.final_conv.1.weight"], initial["diffusion.unet.final_conv.1.weight"])

    # Step 0's all-reduced gradient equals the single-process average of the two ranks' Eq. 9 losses,
    # each holding the KL once: so the KL enters the update once, not once per process.
    config = tiny_config(kl_weight=0.5)
    policy = PacdpPolicy(config)
    policy.load_state_dict(torch.load(tmp_path / "initial.pt"))
    policy.train()
    for rank in (0, 1):
        torch.manual_seed(1000)
        loss, _ = policy.forward(random_batch(config, seed=rank))
        (loss / 2).backward()
    ddp_grads = torch.load(tmp_path / "grads_step0.pt")
    trained = {name: param for name, param in policy.named_parameters() if param.requires_grad}
    assert ddp_grads.keys() == trained.keys()
    for name, param in trained.items():
        assert torch.allclose(ddp_grads[name], param.grad, rtol=1e-4, atol=1e-6), name
    rho_grad = policy.trained_diffusion.unet.final_conv[1].weight_rho.grad
    assert rho_grad.abs().sum() > 0
