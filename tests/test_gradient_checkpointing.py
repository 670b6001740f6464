"""`--policy.gradient_checkpointing=true` trains the same network as without it (issue 10, item 1)."""

import torch

from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import random_batch, tiny_config


def _gradients_and_block_calls(gradient_checkpointing: bool) -> tuple[dict[str, torch.Tensor], int]:
    torch.manual_seed(0)
    policy = PacdpPolicy(tiny_config(down_dims=(16, 32, 64), gradient_checkpointing=gradient_checkpointing))
    unet = policy.trained_diffusion.unet
    with torch.no_grad():  # sigma large enough that a pass on mu gives clearly different gradients
        for name, param in unet.named_parameters():
            if name.endswith("_rho"):
                param.fill_(-2.0)
    calls = []
    unet.down_modules[0][0].conv1.register_forward_hook(lambda *_: calls.append(1))
    policy.train()
    torch.manual_seed(1)  # the same weight sample, diffusion steps and noise in both runs
    loss, _ = policy.forward(random_batch(policy.config))
    loss.backward()
    grads = {name: p.grad for name, p in policy.named_parameters() if p.grad is not None}
    return grads, len(calls)


def test_gradient_checkpointing_gives_exactly_the_gradients_of_the_run_without_it():
    plain, plain_calls = _gradients_and_block_calls(False)
    checkpointed, checkpointed_calls = _gradients_and_block_calls(True)
    assert (plain_calls, checkpointed_calls) == (1, 2)  # the residual block really was recomputed in backward
    assert plain.keys() == checkpointed.keys() and any(name.endswith("_rho") for name in plain)
    differing = [name for name in plain if not torch.equal(plain[name], checkpointed[name])]
    assert differing == []
