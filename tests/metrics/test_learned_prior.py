"""A PAC-DP prior centred on a checkpoint trained on a disjoint split, fine-tunable by lerobot-train, and
`pacdp-certify --prior` checking that the fine-tuned checkpoint kept that prior and its fixed tensors."""

import json
import shutil

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_policy
from safetensors.torch import load_file, save_file

from lerobot_pacdp.bayesian_layers import bayesian_layers, kl_divergence
from lerobot_pacdp.metrics import certificate
from lerobot_pacdp.metrics.checkpoints import MetricsError, load_policy
from lerobot_pacdp.metrics.learned_prior import (
    PROVENANCE_FILE,
    build_learned_prior,
    check_disjoint_from_prior,
)
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from metrics_testing import REPO_ID, diffusion_config, perturb, save_checkpoint
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
    drop = policy.config.drop_n_last_frames
    assert policy.config.num_train_samples == split_b.num_frames - 3 * drop  # N: split B's training windows
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


@pytest.fixture(scope="module")
def split_runs(tiny_dataset, tmp_path_factory):
    """DP on split A (demos 0-2) -> prior; PAC-DP fine-tuned from it on split B (demos 3-5); a second prior."""
    base = tmp_path_factory.mktemp("split")
    priors = []
    for seed in (10, 11):
        torch.manual_seed(seed)
        dp = DiffusionPolicy(diffusion_config())
        perturb(dp, seed)
        source = save_checkpoint(dp, tiny_dataset, base / f"dp_A{seed}" / "checkpoints" / "000100" / "pretrained_model",
                                 episodes=[0, 1, 2])  # fmt: skip
        priors.append(build_learned_prior(source, base / f"prior_A{seed}"))
    policy = PacdpPolicy.from_pretrained(priors[0])
    assert policy.config.freeze_deterministic  # pacdp-learned-prior's default
    policy.config.pretrained_path = priors[0]  # what `lerobot-train --policy.path=<prior>` records
    perturb(policy, seed=12)  # stand-in for fine-tuning: mu and rho move; prior and deterministic tensors do not
    checkpoint = save_checkpoint(policy, tiny_dataset, base / "pacdp_B" / "checkpoints" / "000100" / "pretrained_model",
                                 episodes=[3, 4, 5])  # fmt: skip
    return checkpoint, priors


def _certify(argv, capsys, expected_rc=2):
    assert certificate.main([*argv, "--num_weight_samples=2"]) == expected_rc
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return captured.out if expected_rc == 0 else captured.err.splitlines()[-1]


def test_certify_accepts_a_checkpoint_fine_tuned_from_its_prior(split_runs, tmp_path, capsys):
    checkpoint, (prior, _) = split_runs
    out = _certify([f"--checkpoint={checkpoint}", f"--prior={prior}", f"--output={tmp_path / 'c.json'}"], capsys, 0)
    assert f"prior, deterministic tensors and normalisation = those of the prior {prior}" in out
    report = json.loads((tmp_path / "c.json").read_text())
    assert report["train_episodes"] == [3] and report["heldout_episodes"] == [4, 5] and report["pac_bayes"]["kl"] > 0


def test_certify_refuses_a_prior_whose_tensors_differ(split_runs, capsys):
    checkpoint, (_, other_prior) = split_runs
    err = _certify([f"--checkpoint={checkpoint}", f"--prior={other_prior}"], capsys)
    assert "the prior tensors (prior means and prior rho) of" in err and f"not those of the prior {other_prior}" in err
    assert "_prior_mu (max |difference|" in err and "tensors differ" in err


def test_certify_without_its_prior_refuses_a_run_fine_tuned_from_a_learned_prior(split_runs, capsys):
    checkpoint, (prior, _) = split_runs
    err = _certify([f"--checkpoint={checkpoint}"], capsys)
    assert f"was fine-tuned from the learned prior {prior}: pass --prior={prior}" in err


@pytest.mark.parametrize("what", ["deterministic", "normalisation"])
def test_certify_refuses_fixed_tensors_that_moved_away_from_the_prior(split_runs, tmp_path, capsys, what):
    checkpoint, (prior, _) = split_runs
    moved = shutil.copytree(checkpoint.parents[2], tmp_path / "run") / "checkpoints" / "000100" / "pretrained_model"
    if what == "deterministic":
        file, key = moved / "model.safetensors", "diffusion.unet.mid_modules.0.cond_encoder.1.weight"
    else:
        file = next(moved.glob("policy_preprocessor*normalizer*.safetensors"))
        key = next(k for k in load_file(file) if k.startswith("action."))
    tensors = load_file(file)
    tensors[key] = tensors[key] + 0.25
    save_file(tensors, file)
    err = _certify([f"--checkpoint={moved}", f"--prior={prior}"], capsys)
    expected = "deterministic tensors" if what == "deterministic" else "normalisation statistics"
    assert f"the {expected} of {moved} are not those of the prior" in err and "(max |difference| 0.25)" in err
