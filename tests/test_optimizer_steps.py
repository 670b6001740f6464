"""PAC-DP's optimizer groups ask for torch's fused Adam step, through LeRobot's own optimizer preset and resume."""

import pytest
import torch
from lerobot.optim.optimizers import load_optimizer_state, save_optimizer_state

from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import random_batch, tiny_config


def _policy_and_preset_optimizer(bayesian: bool, fused: bool) -> tuple[PacdpPolicy, torch.optim.Optimizer]:
    torch.manual_seed(0)
    policy = PacdpPolicy(tiny_config(bayesian=bayesian))
    groups = [{**group, "fused": fused} for group in policy.get_optim_params()]
    return policy, policy.config.get_optimizer_preset().build(groups)


def _train(policy: PacdpPolicy, optimizer: torch.optim.Optimizer, steps: range) -> None:
    policy.train()
    for step in steps:
        torch.manual_seed(step)
        loss, _ = policy.forward(random_batch(policy.config, seed=step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


@pytest.mark.parametrize("bayesian", [True, False], ids=["pacdp", "twin"])
def test_lerobots_preset_builds_a_fused_adam_that_steps_like_the_loop_one(bayesian):
    policy, _ = _policy_and_preset_optimizer(bayesian, fused=False)
    assert all(group["fused"] is True for group in policy.get_optim_params())
    runs = {}
    for fused in (True, False):
        policy, optimizer = _policy_and_preset_optimizer(bayesian, fused)
        assert isinstance(optimizer, torch.optim.Adam)
        assert [group["fused"] for group in optimizer.param_groups] == [fused] * len(optimizer.param_groups)
        _train(policy, optimizer, range(3))
        runs[fused] = policy.trained_diffusion.state_dict()
    for name, value in runs[True].items():
        assert torch.allclose(value, runs[False][name], rtol=1e-5, atol=1e-7), name


def test_a_resumed_fused_optimizer_continues_exactly(tmp_path):
    policy, optimizer = _policy_and_preset_optimizer(bayesian=True, fused=True)
    _train(policy, optimizer, range(2))
    save_optimizer_state(optimizer, tmp_path)
    weights = {k: v.clone() for k, v in policy.state_dict().items()}
    _train(policy, optimizer, range(2, 3))
    uninterrupted = policy.trained_diffusion.state_dict()

    resumed_policy, resumed = _policy_and_preset_optimizer(bayesian=True, fused=True)
    resumed_policy.load_state_dict(weights)
    resumed = load_optimizer_state(resumed, tmp_path)
    assert all(group["fused"] is True for group in resumed.param_groups)
    _train(resumed_policy, resumed, range(2, 3))
    for name, value in resumed_policy.trained_diffusion.state_dict().items():
        assert torch.equal(value, uninterrupted[name]), name
