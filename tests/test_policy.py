import json
import math

import pytest
import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from safetensors.torch import load_file, save_file

from lerobot_pacdp.bayesian_layers import BayesianLayer, kl_divergence
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import CheckpointMismatchError, PacdpPolicy
from lerobot_pacdp.objective import pac_bayes_objective

from pacdp_testing import ENV_DIM, STATE_DIM, random_batch, tiny_config, train_steps

BAYESIAN_SUFFIXES = ("_rho", "_prior_mu", "prior_rho")


def _policy(seed: int = 0, **overrides) -> PacdpPolicy:
    torch.manual_seed(seed)
    return PacdpPolicy(tiny_config(**overrides))


def _observation(batch_size: int = 3, seed: int = 5) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "observation.state": torch.randn(batch_size, STATE_DIM, generator=g),
        "observation.environment_state": torch.randn(batch_size, ENV_DIM, generator=g),
    }


def test_paper_defaults():
    config = PacdpConfig()
    assert (config.horizon, config.n_obs_steps, config.n_action_steps) == (16, 2, 8)
    assert config.down_dims == (256, 512, 1024) and config.kernel_size == 5
    assert config.diffusion_step_embed_dim == 256 and config.num_train_timesteps == 100
    assert config.beta_schedule == "squaredcos_cap_v2" and config.prediction_type == "epsilon"
    assert config.noise_scheduler_type == "DDIM" and config.num_inference_steps == 10
    assert (config.prior_rho, config.delta, config.inference_mode) == (-4.5, 0.025, "mean")
    assert config.normalization_mapping["ENV"].value == "MIN_MAX"
    assert config.do_mask_loss_for_padding and not config.bayesian_conditioning
    assert config.type == "pacdp"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("kl_weight", -1e-4, "kl_weight"),
        ("kl_weight", math.nan, "kl_weight"),
        ("delta", 0.0, "delta"),
        ("delta", 1.0, "delta"),
        ("num_train_samples", 0, "num_train_samples"),
        ("prior_rho", math.inf, "prior_rho"),
        ("prior_rho", math.nan, "prior_rho"),
        ("inference_mode", "median", "inference_mode"),
        ("compile_model", True, "compile_model"),
    ],
)
def test_invalid_config_values_fail_at_construction_naming_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        PacdpConfig(**{field: value})


def test_unet_layers_are_bayesian_except_film_projections():
    policy = _policy()
    layers = dict(policy.unet.named_modules())
    bayesian = {n for n, m in layers.items() if isinstance(m, BayesianLayer)}
    film = {n for n in layers if n.endswith("cond_encoder.1")}
    convs_and_linears = {
        n for n, m in layers.items() if isinstance(m, (torch.nn.Linear, torch.nn.Conv1d, torch.nn.ConvTranspose1d))
    }
    assert film and film.isdisjoint(bayesian)
    assert bayesian == convs_and_linears - film
    assert "diffusion_step_encoder.1" in bayesian and "final_conv.1" in bayesian
    assert any(isinstance(layers[n], torch.nn.ConvTranspose1d) for n in bayesian)
    # GroupNorm stays deterministic.
    assert all(not isinstance(m, BayesianLayer) for m in layers.values() if isinstance(m, torch.nn.GroupNorm))


def test_full_bn_ablation_makes_film_projections_bayesian_too():
    policy = _policy(bayesian_conditioning=True)
    layers = dict(policy.unet.named_modules())
    assert all(isinstance(layers[n], BayesianLayer) for n in layers if n.endswith("cond_encoder.1"))


def test_training_forward_returns_eq9_and_logs_its_parts():
    policy = _policy(kl_weight=0.5)
    policy.train()
    loss, logs = policy.forward(random_batch(policy.config))
    assert set(logs) == {"denoise_loss", "kl", "bound_sqrt_term", "bound_linear_term", "sigma_mean"}
    assert all(isinstance(v, float) for v in logs.values())
    assert logs["kl"] == 0.0
    expected = pac_bayes_objective(
        torch.tensor(logs["denoise_loss"], dtype=torch.float64), torch.tensor(0.0), 1000, 0.025, 0.5
    )
    assert loss.item() == pytest.approx(expected.total.item(), rel=1e-6)
    assert logs["sigma_mean"] == pytest.approx(math.log1p(math.exp(-4.5)), rel=1e-6)


def test_kl_is_zero_at_init_and_positive_after_a_step_and_gradients_reach_mu_and_rho():
    policy = _policy(kl_weight=1e-3)
    policy.train()
    trained = policy.trained_diffusion.unet
    assert kl_divergence(trained).item() == 0.0
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=1e-3)
    loss, _ = policy.forward(random_batch(policy.config))
    loss.backward()
    layer = trained.final_conv[1]
    assert layer.weight.grad.abs().sum() > 0 and layer.weight_rho.grad.abs().sum() > 0
    optimizer.step()
    assert kl_divergence(trained).item() > 0


def test_optimizer_groups_exempt_rho_from_weight_decay():
    policy = _policy()
    groups = policy.get_optim_params()
    assert groups[1]["weight_decay"] == 0.0
    assert all(p.shape == q.shape for p, q in zip(groups[1]["params"], groups[1]["params"], strict=True))
    names = {id(p): n for n, p in policy.named_parameters()}
    assert all(names[id(p)].endswith("_rho") for p in groups[1]["params"])
    assert not any(names[id(p)].endswith("_rho") for p in groups[0]["params"])
    trained = [n for n, p in policy.named_parameters() if p.requires_grad]
    assert trained and all(n.startswith("raw_diffusion.") for n in trained)  # the EMA copy is not optimised
    assert len(groups[0]["params"]) + len(groups[1]["params"]) == len(trained)


def test_eval_forward_is_the_posterior_mean_denoising_error():
    policy = _policy()
    policy.eval()
    batch = random_batch(policy.config)
    torch.manual_seed(11)
    loss, logs = policy.forward(batch)
    torch.manual_seed(11)
    plain = policy.diffusion.compute_loss(batch)
    assert set(logs) == {"denoise_loss"}
    assert loss.item() == pytest.approx(plain.item(), rel=1e-6)


def test_training_loss_masks_padded_actions():
    policy = _policy()
    batch = random_batch(policy.config)
    batch["action"][0, -2:] = 1e6  # padded steps of example 0: must not enter the loss
    policy.eval()
    loss, _ = policy.forward(batch)
    assert loss.item() < 100


def _plain_diffusion_copy(policy: PacdpPolicy) -> DiffusionPolicy:
    plain = DiffusionPolicy(policy.config.diffusion_twin())
    missing, unexpected = plain.load_state_dict(policy.state_dict(), strict=False)
    assert missing == []
    training_only = [k for k in unexpected if k.startswith("raw_diffusion.") or k == "num_updates"]
    assert training_only and all(k.endswith(BAYESIAN_SUFFIXES) for k in set(unexpected) - set(training_only))
    return plain.eval()


def test_mean_mode_actions_equal_a_plain_diffusion_policy_with_weights_mu():
    policy = _policy()
    train_steps(policy, 3)  # move mu (and its EMA) away from the prior so the check is not trivial
    policy.eval()
    plain = _plain_diffusion_copy(policy)
    obs = _observation()
    noise = torch.randn(3, policy.config.horizon, 2)
    policy.reset()
    plain.reset()
    ours = policy.select_action(dict(obs), noise=noise)
    theirs = plain.select_action(dict(obs), noise=noise)
    assert torch.allclose(ours, theirs, atol=1e-6)


def test_sample_mode_fixes_weights_within_a_chunk_and_varies_them_across_chunks():
    policy = _policy(inference_mode="sample")
    policy.eval()
    layer = policy.unet.final_conv[1]
    with torch.no_grad():
        for name, p in policy.unet.named_parameters():
            if name.endswith("_rho"):
                p.fill_(-1.0)  # large sigma so different samples are clearly different
    used: list[torch.Tensor] = []
    layer.register_forward_hook(lambda m, i, o: used.append(m.current("weight").detach().clone()))
    obs = _observation()
    noise = torch.randn(3, policy.config.horizon, 2)
    first = policy.predict_action_chunk({k: v.unsqueeze(1).repeat(1, 2, 1) for k, v in obs.items()}, noise=noise)
    n_steps = policy.config.num_inference_steps
    assert len(used) == n_steps
    assert all(torch.equal(w, used[0]) for w in used)
    second = policy.predict_action_chunk({k: v.unsqueeze(1).repeat(1, 2, 1) for k, v in obs.items()}, noise=noise)
    assert len(used) == 2 * n_steps
    assert not torch.equal(used[0], used[n_steps])
    assert not torch.allclose(first, second)
    # After the chunk the network is back on its posterior mean.
    assert layer.current("weight") is layer.weight


def test_mean_mode_is_deterministic_across_chunks():
    policy = _policy()
    policy.eval()
    batch = {k: v.unsqueeze(1).repeat(1, 2, 1) for k, v in _observation().items()}
    noise = torch.randn(3, policy.config.horizon, 2)
    assert torch.equal(policy.predict_action_chunk(batch, noise=noise), policy.predict_action_chunk(batch, noise=noise))


def test_save_load_round_trip_restores_mu_rho_and_prior_exactly(tmp_path):
    policy = _policy(kl_weight=1e-3)
    train_steps(policy, 3)
    policy.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["type"] == "pacdp" and saved["num_train_samples"] == 1000 and saved["kl_weight"] == 1e-3
    torch.manual_seed(123)  # a different seed: the prior must come from the file, not the RNG
    loaded = PacdpPolicy.from_pretrained(tmp_path)
    original, restored = policy.state_dict(), loaded.state_dict()
    assert original.keys() == restored.keys()
    assert any(k.endswith("_prior_mu") for k in restored)
    for key in original:
        assert torch.equal(original[key], restored[key]), key
    assert kl_divergence(loaded.unet).item() == pytest.approx(kl_divergence(policy.unet).item(), rel=1e-12)


@pytest.mark.parametrize("corruption", ["drop_rho", "extra_key"])
def test_loading_a_checkpoint_with_mismatched_bayesian_keys_fails_loudly(tmp_path, corruption):
    policy = _policy()
    policy.save_pretrained(tmp_path)
    tensors = load_file(tmp_path / "model.safetensors")
    if corruption == "drop_rho":
        tensors = {k: v for k, v in tensors.items() if not k.endswith("final_conv.1.weight_rho")}
    else:
        tensors["diffusion.unet.final_conv.1.extra_rho"] = torch.zeros(1)
    save_file(tensors, tmp_path / "model.safetensors")
    with pytest.raises(CheckpointMismatchError, match="does not match this PAC-DP network"):
        PacdpPolicy.from_pretrained(tmp_path)


def test_training_without_n_explains_how_to_set_it():
    policy = _policy(num_train_samples=None)
    policy.train()
    with pytest.raises(ValueError, match="num_train_samples"):
        policy.forward(random_batch(policy.config))
