"""`bayesian=false`: the DP baseline that differs from PAC-DP only in what the paper changes."""

import math

import pytest
import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

from lerobot_pacdp.bayesian_layers import BayesianLayer
from lerobot_pacdp.modeling_pacdp import NonFiniteTrainingError, PacdpPolicy

from pacdp_testing import random_batch, tiny_config


def test_one_training_step_equals_lerobots_diffusion_with_the_equivalent_config_and_seed():
    config = tiny_config(bayesian=False, use_ema=False)
    torch.manual_seed(0)
    twin = PacdpPolicy(config)
    torch.manual_seed(0)
    plain = DiffusionPolicy(config.diffusion_twin())
    assert not any(isinstance(m, BayesianLayer) for m in twin.modules())
    assert twin.state_dict().keys() - {"num_updates"} == plain.state_dict().keys()
    batch = random_batch(config)
    losses, grads = [], []
    for policy in (twin, plain):
        policy.train()
        torch.manual_seed(5)  # the same diffusion noise and timesteps
        loss, _ = policy.forward(batch)
        loss.backward()
        losses.append(loss.item())
        grads.append({n: p.grad for n, p in policy.named_parameters()})
    assert losses[0] == losses[1]
    assert grads[0].keys() == grads[1].keys()
    assert all(torch.equal(grads[0][n], grads[1][n]) for n in grads[0])
    params = [dict(policy.named_parameters()) for policy in (twin, plain)]
    groups = twin.get_optim_params()
    assert [id(p) for p in groups[0]["params"]] == [id(p) for p in params[0].values()]


def test_pacdp_config_and_its_diffusion_twin_convert_both_ways_keeping_every_shared_field():
    from dataclasses import fields

    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    from lerobot_pacdp.configuration_pacdp import PacdpConfig

    config = tiny_config(kl_weight=3e-3, prior_rho=-3.0, horizon=8, noise_scheduler_type="DDPM")
    twin = config.diffusion_twin()
    assert type(twin) is DiffusionConfig
    shared = [f.name for f in fields(DiffusionConfig) if f.init]
    assert all(getattr(twin, name) == getattr(config, name) for name in shared)
    back = PacdpConfig.from_diffusion(twin, kl_weight=5e-5)
    assert all(getattr(back, name) == getattr(config, name) for name in shared)
    assert back.kl_weight == 5e-5 and back.prior_rho == PacdpConfig().prior_rho  # a diffusion config has none
    again = PacdpConfig.from_diffusion(config)  # a pacdp config keeps its PAC-Bayes fields
    assert (again.kl_weight, again.prior_rho) == (3e-3, -3.0)


def test_the_twin_logs_its_denoising_loss_and_trains_with_ema_by_default():
    policy = PacdpPolicy(tiny_config(bayesian=False))
    policy.train()
    loss, logs = policy.forward(random_batch(policy.config))
    assert logs == {"denoise_loss": pytest.approx(loss.item())}
    assert policy.raw_diffusion is not None


def test_sample_mode_without_a_posterior_is_refused():
    with pytest.raises(ValueError, match="inference_mode='sample'.*bayesian=False"):
        tiny_config(bayesian=False, inference_mode="sample")


@pytest.mark.parametrize("bayesian", [True, False])
def test_a_non_finite_loss_stops_training_naming_the_step_and_the_term(bayesian):
    policy = PacdpPolicy(tiny_config(bayesian=bayesian))
    policy.train()
    batch = random_batch(policy.config)
    batch["action"][1, 3, 0] = math.nan
    with pytest.raises(NonFiniteTrainingError, match=r"training step 1: denoise_loss = nan.*non-finite: denoise_loss.*batch holds NaN"):
        policy.forward(batch)


def test_weights_made_non_finite_by_a_step_stop_the_next_step_and_are_never_saved(tmp_path):
    policy = PacdpPolicy(tiny_config())
    with torch.no_grad():
        policy.trained_diffusion.unet.final_conv[1].weight[0, 0, 0] = math.inf
    policy.update()  # the EMA takes the bad weight (update 0 copies), as after a non-finite gradient
    policy.train()
    with pytest.raises(NonFiniteTrainingError, match="step 2: .*already non-finite: the previous optimizer step"):
        policy.forward(random_batch(policy.config))
    with pytest.raises(NonFiniteTrainingError, match="refusing to save a checkpoint after update 1: 2 tensors"):
        policy.save_pretrained(tmp_path / "checkpoint")
    assert not (tmp_path / "checkpoint" / "model.safetensors").exists()
