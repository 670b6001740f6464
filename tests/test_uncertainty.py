"""The posterior uncertainty of an action chunk (`lerobot_pacdp.uncertainty`, `PacdpPolicy.predict_with_uncertainty`)."""

import copy

import pytest
import torch

from lerobot_pacdp.bayesian_layers import BayesianLayer, softplus_inverse
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy
from lerobot_pacdp.uncertainty import action_spread, posterior_weight_samples

from pacdp_testing import ACTION_DIM, ENV_DIM, STATE_DIM, tiny_config


def _policy(seed: int = 0, **overrides) -> PacdpPolicy:
    torch.manual_seed(seed)
    return PacdpPolicy(tiny_config(**overrides)).eval()


def _window(policy: PacdpPolicy, batch_size: int = 3, seed: int = 5) -> dict[str, torch.Tensor]:
    """An observation window (B, n_obs_steps, dim), as `predict_action_chunk` takes it offline."""
    g = torch.Generator().manual_seed(seed)
    n_obs = policy.config.n_obs_steps
    return {
        "observation.state": torch.randn(batch_size, n_obs, STATE_DIM, generator=g),
        "observation.environment_state": torch.randn(batch_size, n_obs, ENV_DIM, generator=g),
    }


def _set_sigma(policy: PacdpPolicy, sigma: float) -> None:
    with torch.no_grad():
        for layer in policy.unet.modules():
            if isinstance(layer, BayesianLayer):
                for name, rho in layer.named_parameters(recurse=False):
                    if name.endswith("_rho"):
                        rho.fill_(softplus_inverse(sigma) if sigma > 1e-6 else -40.0)


def test_action_spread_is_the_rms_across_sample_standard_deviation():
    chunks = torch.zeros(2, 1, 2, 2)  # K=2, B=1, T=2, D=2
    chunks[1] = 1.0  # every element: values 0 and 1, variance (K - 1 denominator) 0.5
    chunks[1, 0, 0, 0] = 3.0  # one element: values 0 and 3, variance 4.5
    assert action_spread(chunks).tolist() == pytest.approx([((0.5 * 3 + 4.5) / 4) ** 0.5])


def test_the_posterior_spread_vanishes_as_sigma_goes_to_zero_and_grows_with_sigma():
    policy = _policy()
    window, noise = _window(policy), torch.randn(3, policy.config.horizon, ACTION_DIM)
    posterior, noise_spread = [], []
    for sigma in (0.0, 1e-3, 1e-2, 1e-1):
        _set_sigma(policy, sigma)
        chunk = policy.predict_with_uncertainty(window, noise, num_samples=6, generator=torch.Generator().manual_seed(1))
        posterior.append(chunk.posterior)
        noise_spread.append(chunk.noise)
    assert posterior[0].abs().max() < 1e-6
    assert all(torch.all(a < b) for a, b in zip(posterior, posterior[1:], strict=False))
    assert posterior[1].min() > 1e-5
    # the noise baseline uses the posterior mean, which sigma does not move
    assert all(torch.equal(noise_spread[0], other) for other in noise_spread[1:]) and noise_spread[0].min() > 0


def test_the_batched_weight_sets_give_the_chunks_of_one_pass_per_weight_sample():
    policy = _policy()
    _set_sigma(policy, 0.05)
    window, noise, k = _window(policy), torch.randn(3, policy.config.horizon, ACTION_DIM), 4
    chunk = policy.predict_with_uncertainty(window, noise, num_samples=k, generator=torch.Generator().manual_seed(7))

    weights = posterior_weight_samples(policy.unet, k, torch.Generator().manual_seed(7))  # the same first draws
    model = policy.diffusion
    chunks = []
    for i in range(k):
        sample = copy.deepcopy(model)
        with torch.no_grad():
            for name, value in weights.items():
                sample.unet.get_parameter(name).copy_(value[i])
        chunks.append(sample.generate_actions(window, noise=noise.clone()))
    assert torch.allclose(chunk.posterior, action_spread(torch.stack(chunks)), atol=1e-5)
    assert torch.equal(chunk.actions, model.generate_actions(window, noise=noise.clone()))


@pytest.mark.parametrize("mode", ["mean", "sample"])
def test_actions_and_the_global_rng_are_unchanged_with_the_uncertainty_on(mode):
    policy = _policy(inference_mode=mode)
    observation = {k: v[:, -1] for k, v in _window(policy).items()}

    def act(samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        policy.config.uncertainty_samples = samples
        torch.manual_seed(3)
        policy.reset()
        actions = torch.stack([policy.select_action(dict(observation)) for _ in range(9)])
        return actions, torch.get_rng_state()

    actions_off, rng_off = act(0)
    assert policy.uncertainty_trace == []
    actions_on, rng_on = act(4)
    assert torch.equal(actions_off, actions_on) and torch.equal(rng_off, rng_on)
    assert len(policy.uncertainty_trace) == 3  # 9 steps, a chunk of 4 actions every 4 steps
    assert all(c.posterior.shape == c.noise.shape == (3,) for c in policy.uncertainty_trace)


def test_the_dp_twin_has_a_noise_spread_and_no_posterior_spread():
    policy = _policy(bayesian=False)
    chunk = policy.predict_with_uncertainty(_window(policy), num_samples=3)
    assert chunk.posterior is None and chunk.noise.shape == (3,) and chunk.noise.min() > 0


@pytest.mark.parametrize("value", [-1, 1])
def test_uncertainty_samples_must_be_zero_or_at_least_two(value):
    with pytest.raises(ValueError, match=f"`uncertainty_samples` must be 0 .* got {value}"):
        PacdpConfig(uncertainty_samples=value)
    assert PacdpConfig(uncertainty_samples=2).uncertainty_samples == 2
