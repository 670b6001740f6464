"""Run under `torchrun --nproc_per_node 2`: a few PAC-DP steps with LeRobot's DDP settings.

Writes (rank 0) the initial state, the all-reduced gradients of step 0, and every rank's final
parameters (trained and EMA) to the directory given as argv[1], for tests/test_distributed.py to check.
"""

import sys
from pathlib import Path

import torch
from accelerate import Accelerator
from accelerate.utils import DistributedDataParallelKwargs

from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import random_batch, tiny_config

STEPS = 3


def main(out_dir: Path) -> None:
    accelerator = Accelerator(cpu=True, kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=True)])
    rank = accelerator.process_index
    torch.manual_seed(0)  # lerobot's set_seed gives every rank the same seed
    config = tiny_config(kl_weight=0.5)
    policy = PacdpPolicy(config)
    with torch.no_grad():  # move Q away from P so the KL and its gradient are not zero
        for name, p in policy.trained_diffusion.unet.named_parameters():
            p.add_(0.3 if name.endswith("_rho") else 0.01 * torch.randn_like(p))
    if rank == 0:
        torch.save(policy.state_dict(), out_dir / "initial.pt")
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=1e-3)
    policy.train()
    policy, optimizer = accelerator.prepare(policy, optimizer)
    for step in range(STEPS):
        batch = random_batch(config, seed=100 * step + rank)
        torch.manual_seed(1000 + step)  # same weight sample and diffusion noise on every rank
        loss, _ = policy.forward(batch)
        accelerator.backward(loss)
        if step == 0 and rank == 0:
            named = accelerator.unwrap_model(policy).named_parameters()
            grads = {n: p.grad.clone() for n, p in named if p.grad is not None}
            torch.save(grads, out_dir / "grads_step0.pt")
        optimizer.step()
        optimizer.zero_grad()
        accelerator.unwrap_model(policy).update()  # as lerobot-train does: the EMA step
    params = {n: p.detach().clone() for n, p in accelerator.unwrap_model(policy).named_parameters()}
    torch.save(params, out_dir / f"final_rank{rank}.pt")
    accelerator.wait_for_everyone()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
