"""`freeze_deterministic`: only the posterior trains, and every other tensor keeps a reference fixed in advance."""

import pytest
import torch

from lerobot_pacdp.certification import (
    REFERENCE_SEED,
    TensorDifference,
    data_free_reference,
    describe_differences,
    deterministic_tensors,
    prior_tensors,
    tensor_differences,
)
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import tiny_config, train_steps


def test_the_deterministic_tensors_are_groupnorm_and_the_film_projections():
    policy = PacdpPolicy(tiny_config())
    names = deterministic_tensors(policy.diffusion)
    assert len(names) == 50 and all(".block.1." in n or ".cond_encoder.1." in n for n in names)
    assert any(".cond_encoder.1.weight" in n for n in names)
    priors = prior_tensors(policy.diffusion)
    assert priors and all(n.endswith(("_prior_mu", "prior_rho")) for n in priors)
    full_bn = PacdpPolicy(tiny_config(bayesian_conditioning=True))  # the FiLM projections are Bayesian there
    assert not any("cond_encoder" in n for n in deterministic_tensors(full_bn.diffusion))


def test_freeze_starts_at_the_data_free_reference_whatever_the_seed_and_keeps_the_callers_stream():
    policies = []
    for seed in (1, 2):
        torch.manual_seed(seed)
        policies.append(PacdpPolicy(tiny_config(freeze_deterministic=True)))
        after = torch.rand(3)
        torch.manual_seed(seed)
        PacdpPolicy(tiny_config())
        assert torch.equal(after, torch.rand(3))  # building the reference did not consume the global stream
    reference = data_free_reference(policies[0].config)
    for policy in policies:
        assert tensor_differences(deterministic_tensors(policy.diffusion), reference) == []
        assert tensor_differences(deterministic_tensors(policy.raw_diffusion), reference) == []  # the EMA's copy
    # The prior itself is still drawn from the caller's seed.
    assert tensor_differences(prior_tensors(policies[0].diffusion), prior_tensors(policies[1].diffusion))
    torch.manual_seed(REFERENCE_SEED + 1)
    assert tensor_differences(deterministic_tensors(PacdpPolicy(tiny_config()).diffusion), reference)


def test_training_with_freeze_moves_only_the_posterior():
    torch.manual_seed(0)
    frozen, free = PacdpPolicy(tiny_config(freeze_deterministic=True)), PacdpPolicy(tiny_config())
    before = {name: {k: v.clone() for k, v in deterministic_tensors(p.diffusion).items()} for name, p in
              (("frozen", frozen), ("free", free))}  # fmt: skip
    mu_before = frozen.raw_diffusion.unet.final_conv[1].weight.clone()
    trained = {id(p) for group in frozen.get_optim_params() for p in group["params"]}
    assert not any(id(p) in trained for p in frozen.raw_diffusion.parameters() if not p.requires_grad)
    train_steps(frozen, 3)
    train_steps(free, 3)
    for network in (frozen.diffusion, frozen.raw_diffusion):  # bitwise, in the average and the trained copy
        assert tensor_differences(deterministic_tensors(network), before["frozen"]) == []
    assert not torch.equal(frozen.raw_diffusion.unet.final_conv[1].weight, mu_before)  # the posterior trained
    moved = tensor_differences(deterministic_tensors(free.raw_diffusion), before["free"])
    assert len(moved) == 50  # without the option every deterministic tensor trains


def test_a_policy_without_a_posterior_cannot_freeze_everything():
    with pytest.raises(ValueError, match="`freeze_deterministic=True`.*`bayesian=False`.*nothing would train"):
        tiny_config(bayesian=False, freeze_deterministic=True)


def test_differences_name_the_tensor_and_the_largest_gap_first():
    reference = {"a": torch.zeros(3), "b": torch.zeros(2), "c": torch.ones(1), "d": torch.zeros(2, 2)}
    actual = {"a": torch.tensor([0.0, 0.5, -2.0]), "b": torch.zeros(2), "c": torch.ones(1) + 1e-3, "d": torch.zeros(4),
              "e": torch.zeros(1)}  # fmt: skip
    differences = tensor_differences(actual, reference)
    assert [d.name for d in differences] == ["d", "e", "a", "c"]  # shape and missing first, then by gap
    assert differences[0] == TensorDifference("d", "shape (4,), reference (2, 2)")
    assert differences[2].max_abs_difference == 2.0
    assert differences[3].max_abs_difference == pytest.approx(1e-3, rel=1e-3)
    assert describe_differences(differences, total=5, limit=2) == (
        "4 of 5 tensors differ, e.g. d (shape (4,), reference (2, 2)), e (not in the reference)"
    )
