"""A PAC-DP prior centred on a checkpoint trained on a disjoint split, fine-tunable by lerobot-train."""

import json

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_policy
from safetensors.torch import load_file

from lerobot_pacdp.bayesian_layers import bayesian_layers, kl_divergence
from lerobot_pacdp.metrics import certificate
from lerobot_pacdp.metrics.checkpoints import MetricsError, load_policy
from lerobot_pacdp.metrics.learned_prior import PROVENANCE_FILE, build_learned_prior, check_disjoint_from_prior
from lerobot_pacdp.modeling_pacdp import PacdpPolicy
from metrics_testing import REPO_ID
from pacdp_testing import random_batch


@pytest.fixture(scope="module")
def dp_prior(tiny_runs, tmp_path_factory):
    source = tiny_runs["dp_s0"] / "checkpoints" / "000300" / "pretrained_model"
    out = build_learned_prior(source, tmp_path_factory.mktemp("prior") / "prior_A", prior_rho=-5.0, kl_weight=1e-3)
    return source, out


def test_prior_and_posterior_means_are_the_dp_weights(dp_prior):
    source, out = dp_prior
    weights = load_file(source / "model.safetensors")
    policy = PacdpPolicy.from_pretrained(out)
    assert kl_divergence(policy.unet).item() == 0.0
    state = policy.state_dict()
    for key, value in weights.items():
        assert torch.equal(state[key], value), key  # every mu and deterministic tensor
    layers = list(bayesian_layers(policy.unet))
    assert layers
    prior_sigma = torch.nn.functional.softplus(torch.tensor(-5.0))
    for layer in layers:
        for name in layer._bayesian_param_names():
            assert torch.equal(getattr(layer, f"{name}_prior_mu"), getattr(layer, name))
            assert torch.allclose(layer.posterior_sigma(name), prior_sigma)
    config = policy.config
    assert (config.type, config.prior_rho, config.kl_weight, config.num_train_samples) == ("pacdp", -5.0, 1e-3, None)
    assert "ENV" not in config.normalization_mapping  # the DP's own normalisation is kept


def test_mean_network_acts_exactly_like_the_source_dp(dp_prior):
    source, out = dp_prior
    dp, pacdp = load_policy(source).policy, load_policy(out).policy
    batch = random_batch(pacdp.config, batch_size=3)
    noise = torch.randn(3, pacdp.config.horizon, 2, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(
        pacdp.predict_action_chunk(batch, noise=noise), dp.predict_action_chunk(batch, noise=noise), rtol=0, atol=0
    )


def test_lerobot_train_policy_path_fine_tunes_it_on_split_b(dp_prior, tiny_dataset):
    _, out = dp_prior
    config = PreTrainedConfig.from_pretrained(out)
    config.pretrained_path = out  # what `lerobot-train --policy.path=out` does
    split_b = LeRobotDataset(REPO_ID, root=tiny_dataset.root, episodes=[3, 4, 5])
    policy = make_policy(config, ds_meta=split_b.meta)
    assert policy.config.num_train_samples == split_b.num_frames  # N derived from split B
    assert kl_divergence(policy.unet).item() == 0.0
    policy.train()
    loss, info = policy.forward(random_batch(policy.config))
    assert torch.isfinite(loss) and info["kl"] == 0.0
    for name in ("policy_preprocessor.json", "policy_postprocessor.json"):
        assert (out / name).is_file()


def test_provenance_guards_the_split(dp_prior):
    _, out = dp_prior
    assert json.loads((out / PROVENANCE_FILE).read_text())["prior_episodes"] == [0, 1, 2, 3, 4, 5]
    check_disjoint_from_prior(out, [6, 7])
    with pytest.raises(MetricsError, match="learnt from 2 of the certified"):
        check_disjoint_from_prior(out, [5, 2, 9])


def test_certify_refuses_a_prior_trained_on_the_certified_demos(dp_prior, tiny_runs, capsys):
    _, out = dp_prior
    checkpoint = tiny_runs["pacdp_s0"] / "checkpoints" / "000100"
    assert certificate.main([f"--checkpoint={checkpoint}", f"--prior={out}", "--num_weight_samples=1"]) == 2
    err = capsys.readouterr().err
    assert "certify on a split disjoint" in err and "Traceback" not in err


def test_a_pacdp_source_gives_its_mu_and_a_fresh_rho(tiny_runs, tmp_path):
    source = tiny_runs["pacdp_s0"] / "checkpoints" / "000200"
    weights = load_file(source / "pretrained_model" / "model.safetensors")
    policy = PacdpPolicy.from_pretrained(build_learned_prior(source, tmp_path / "prior"))
    layer_name, layer = next((n, m) for n, m in policy.unet.named_modules() if m in set(bayesian_layers(policy.unet)))
    key = f"diffusion.unet.{layer_name}.weight"
    assert torch.equal(layer.weight_prior_mu, weights[key]) and torch.equal(layer.weight, weights[key])
    assert not torch.equal(layer.weight_rho, weights[f"{key}_rho"])  # the source's rho was perturbed
    assert torch.all(layer.weight_rho == policy.config.prior_rho)
    with pytest.raises(MetricsError, match="not empty"):
        build_learned_prior(source, tmp_path / "prior")
