"""EMA as Diffusion Policy uses it: Chi et al.'s decay, the update, and where the averaged weights act."""

import math

import pytest
import torch
from safetensors.torch import load_file, save_file

from lerobot_pacdp.bayesian_layers import sampled_weights
from lerobot_pacdp.ema import ema_decay, update_ema
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import random_batch, tiny_config, train_steps


def _policy(seed: int = 0, **overrides) -> PacdpPolicy:
    torch.manual_seed(seed)
    return PacdpPolicy(tiny_config(**overrides))


def test_decay_is_chis_warm_up_capped_at_max_decay():
    assert ema_decay(0, 0.75, 0.9999) == 0.0 and ema_decay(1, 0.75, 0.9999) == 0.0
    assert ema_decay(2, 0.75, 0.9999) == pytest.approx(1 - 0.594603558, abs=1e-9)  # (1 + 1)^-0.75
    assert ema_decay(10, 0.75, 0.9999) == pytest.approx(1 - 0.177827941, abs=1e-9)  # (1 + 9)^-0.75
    assert ema_decay(10**9, 0.75, 0.9999) == 0.9999
    assert ema_decay(100, 0.5, 0.95) == pytest.approx(0.9)  # 1 - (1 + 99)^-0.5


def test_update_averages_trained_parameters_and_copies_frozen_ones_and_buffers():
    def module(weight: float, frozen: float, buffer: float, prior: float) -> torch.nn.Module:
        m = torch.nn.Module()
        m.weight = torch.nn.Parameter(torch.tensor([weight]))
        m.frozen = torch.nn.Parameter(torch.tensor([frozen]), requires_grad=False)
        m.register_buffer("running", torch.tensor([buffer]))
        m.register_buffer("weight_prior_mu", torch.tensor([prior]))
        return m

    averaged, trained = module(1.0, 5.0, 7.0, 3.0), module(2.0, 6.0, 8.0, 4.0)
    averaged.requires_grad_(False)
    trained.frozen.requires_grad_(False)
    update_ema(averaged, trained, decay=0.75)
    assert averaged.weight.item() == pytest.approx(0.75 * 1.0 + 0.25 * 2.0)
    assert averaged.frozen.item() == 6.0 and averaged.running.item() == 8.0
    assert averaged.weight_prior_mu.item() == 3.0  # a prior is a constant: never touched


def test_the_acting_weights_follow_the_ema_recurrence_of_the_trained_weights():
    policy = _policy()
    initial = {k: v.detach().clone() for k, v in policy.diffusion.named_parameters()}
    history = train_steps(policy, steps=5)
    expected = initial
    for step, trained in enumerate(history):
        decay = ema_decay(step, 0.75, 0.9999)
        expected = {k: decay * expected[k] + (1 - decay) * trained[k] for k in expected}
    acting = dict(policy.diffusion.named_parameters())
    for key, value in expected.items():
        assert torch.allclose(acting[key], value, atol=1e-6), key
    assert int(policy.num_updates) == 5
    assert not torch.equal(acting["unet.final_conv.1.weight"], history[-1]["unet.final_conv.1.weight"])


def test_eval_forward_and_both_inference_modes_use_the_ema_weights():
    policy = _policy()
    train_steps(policy, steps=4)
    policy.eval()
    batch = random_batch(policy.config)
    torch.manual_seed(3)
    npe, _ = policy.forward(batch)
    torch.manual_seed(3)
    assert npe.item() == pytest.approx(policy.diffusion.compute_loss(batch).item(), rel=1e-6)
    torch.manual_seed(3)
    assert npe.item() != pytest.approx(policy.raw_diffusion.compute_loss(batch).item(), rel=1e-6)

    observation = {k: v for k, v in batch.items() if k.startswith("observation")}
    noise = torch.randn(4, policy.config.horizon, 2)
    assert torch.equal(policy.predict_action_chunk(observation, noise=noise), policy.diffusion.generate_actions(observation, noise=noise))
    policy.config.inference_mode = "sample"
    torch.manual_seed(9)
    sampled = policy.predict_action_chunk(observation, noise=noise)
    torch.manual_seed(9)
    with sampled_weights(policy.diffusion.unet):  # a draw from the averaged posterior
        expected = policy.diffusion.generate_actions(observation, noise=noise)
    assert torch.equal(sampled, expected)


def test_without_ema_the_trained_network_acts():
    policy = _policy(use_ema=False)
    assert policy.raw_diffusion is None and policy.trained_diffusion is policy.diffusion
    history = train_steps(policy, steps=2)
    acting = dict(policy.diffusion.named_parameters())
    assert all(torch.equal(acting[k], v) for k, v in history[-1].items())


def test_save_and_load_restore_trained_weights_ema_and_update_count_exactly(tmp_path):
    policy = _policy()
    train_steps(policy, steps=3)
    policy.save_pretrained(tmp_path)
    saved = load_file(tmp_path / "model.safetensors")
    assert any(k.startswith("raw_diffusion.") for k in saved) and saved["num_updates"].item() == 3
    torch.manual_seed(77)
    loaded = PacdpPolicy.from_pretrained(tmp_path)
    for key, value in policy.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    # Training resumes the average where it was: the next decay is the one for step 3.
    assert int(loaded.num_updates) == 3


def test_a_checkpoint_saved_before_ema_existed_loads_with_the_average_starting_from_its_weights(tmp_path, caplog):
    policy = _policy()
    train_steps(policy, steps=2)
    policy.save_pretrained(tmp_path)
    tensors = load_file(tmp_path / "model.safetensors")
    old = {k: v for k, v in tensors.items() if not k.startswith("raw_diffusion.") and k != "num_updates"}
    save_file(old, tmp_path / "model.safetensors")
    loaded = PacdpPolicy.from_pretrained(tmp_path)
    assert "predates pacdp's EMA" in caplog.text
    raw, acting = loaded.raw_diffusion.state_dict(), loaded.diffusion.state_dict()
    assert all(torch.equal(raw[k], acting[k]) for k in acting) and int(loaded.num_updates) == 0


@pytest.mark.parametrize(
    ("field", "value"),
    [("ema_power", 0.0), ("ema_power", -1.0), ("ema_power", math.nan), ("ema_max_decay", 1.0), ("ema_max_decay", -0.1)],
)
def test_invalid_ema_fields_fail_at_construction_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        tiny_config(**{field: value})
