import math

import pytest
import torch
from torch import nn
from torch.distributions import Normal
from torch.distributions import kl_divergence as torch_kl
from torch.utils.checkpoint import checkpoint

from lerobot_pacdp.bayesian_layers import (
    BayesianConv1d,
    BayesianConvTranspose1d,
    BayesianLinear,
    bayesianize,
    kl_divergence,
    make_bayesian,
    mean_posterior_sigma,
    sampled_weights,
    softplus_inverse,
)

PRIOR_RHO = -4.5


def _layers() -> list[nn.Module]:
    torch.manual_seed(0)
    return [nn.Linear(12, 7), nn.Conv1d(6, 5, 3, padding=1), nn.ConvTranspose1d(4, 4, 4, 2, 1)]


def _perturb(layer: nn.Module) -> None:
    with torch.no_grad():
        for name, param in layer.named_parameters():
            param.add_(0.05 * torch.randn_like(param) if not name.endswith("_rho") else torch.rand_like(param))


@pytest.mark.parametrize("layer", _layers(), ids=lambda m: type(m).__name__)
def test_conversion_keeps_shapes_and_initialises_posterior_to_prior(layer):
    shapes = {n: p.shape for n, p in layer.named_parameters()}
    make_bayesian(layer, PRIOR_RHO)
    assert isinstance(layer, (BayesianLinear, BayesianConv1d, BayesianConvTranspose1d))
    for name, shape in shapes.items():
        assert getattr(layer, name).shape == shape
        assert torch.equal(getattr(layer, name), getattr(layer, f"{name}_prior_mu"))
        assert torch.all(getattr(layer, f"{name}_rho") == PRIOR_RHO)
    assert torch.all(layer.bias_prior_mu == 0)
    assert kl_divergence(layer).item() == 0.0


def test_prior_mean_is_truncated_normal_with_fan_in_scale():
    torch.manual_seed(1)
    layer = make_bayesian(nn.Conv1d(64, 256, 5), PRIOR_RHO)
    std = 1 / math.sqrt(64 * 5)
    w = layer.weight_prior_mu
    assert w.abs().max() <= 2 * std + 1e-7
    # A N(0, s^2) truncated at +-2s has std ~0.880 s.
    assert w.std().item() == pytest.approx(0.880 * std, rel=0.03)
    assert w.mean().item() == pytest.approx(0.0, abs=0.02 * std)


@pytest.mark.parametrize("layer", _layers(), ids=lambda m: type(m).__name__)
def test_kl_matches_torch_distributions(layer):
    make_bayesian(layer, PRIOR_RHO)
    _perturb(layer)
    expected = 0.0
    prior_sigma = nn.functional.softplus(torch.tensor(PRIOR_RHO, dtype=torch.float64))
    for name in ("weight", "bias"):
        q = Normal(getattr(layer, name).double(), layer.posterior_sigma(name).double())
        p = Normal(getattr(layer, f"{name}_prior_mu").double(), prior_sigma)
        expected += torch_kl(q, p).sum().item()
    assert kl_divergence(layer).item() == pytest.approx(expected, rel=1e-5)
    assert kl_divergence(layer).dtype == torch.float64


def test_sampled_weights_have_posterior_mean_and_std():
    torch.manual_seed(2)
    layer = make_bayesian(nn.Linear(50, 40), PRIOR_RHO)
    with torch.no_grad():
        layer.weight_rho.fill_(softplus_inverse(0.2))
    samples = []
    for _ in range(400):
        with sampled_weights(layer):
            samples.append(layer.current("weight").detach().clone())
    stacked = torch.stack(samples)
    assert torch.allclose(stacked.mean(0), layer.weight, atol=0.2 * 4 / math.sqrt(400))
    assert stacked.std(0).mean().item() == pytest.approx(0.2, rel=0.02)
    # Outside the block the layer is back to its posterior mean.
    assert layer.current("weight") is layer.weight


def test_one_sample_is_shared_by_every_call_inside_the_block():
    layer = make_bayesian(nn.Linear(3, 2), PRIOR_RHO)
    x = torch.randn(5, 3)
    with sampled_weights(layer):
        first, second = layer(x), layer(x)
    with sampled_weights(layer):
        third = layer(x)
    assert torch.equal(first, second)
    assert not torch.equal(first, third)
    assert torch.equal(layer(x), nn.functional.linear(x, layer.weight, layer.bias))


def test_gradients_reach_mu_and_rho_through_sample_and_kl():
    torch.manual_seed(3)
    layer = make_bayesian(nn.Conv1d(3, 4, 3, padding=1), PRIOR_RHO)
    with sampled_weights(layer):
        out = layer(torch.randn(2, 3, 8)).square().mean()
    (out + kl_divergence(layer)).backward()
    for name in ("weight", "bias", "weight_rho", "bias_rho"):
        grad = getattr(layer, name).grad
        assert grad is not None and grad.abs().sum() > 0, name


def test_conv_transpose_output_matches_deterministic_layer_at_the_mean():
    torch.manual_seed(4)
    reference = nn.ConvTranspose1d(4, 4, 4, 2, 1)
    bayesian = make_bayesian(nn.ConvTranspose1d(4, 4, 4, 2, 1), PRIOR_RHO)
    reference.load_state_dict({"weight": bayesian.weight, "bias": bayesian.bias})
    x = torch.randn(2, 4, 8)
    assert torch.allclose(bayesian(x), reference(x))


def test_bayesianize_respects_keep_deterministic_and_rejects_unknown_layers():
    net = nn.Sequential(nn.Linear(3, 3), nn.Sequential(nn.Mish(), nn.Linear(3, 3)), nn.GroupNorm(1, 3))
    converted = bayesianize(net, PRIOR_RHO, keep_deterministic=lambda name: name == "1.1")
    assert converted == ["0"]
    assert type(net[1][1]) is nn.Linear and type(net[2]) is nn.GroupNorm
    with pytest.raises(TypeError, match="No Bayesian version of GroupNorm"):
        make_bayesian(nn.GroupNorm(1, 3), PRIOR_RHO)
    with pytest.raises(ValueError, match="no Bayesian layers"):
        kl_divergence(nn.Linear(2, 2))


def test_mean_posterior_sigma_is_softplus_of_rho():
    layer = make_bayesian(nn.Linear(4, 4), PRIOR_RHO)
    assert mean_posterior_sigma(layer) == pytest.approx(math.log1p(math.exp(PRIOR_RHO)), rel=1e-6)
    assert softplus_inverse(math.log1p(math.exp(PRIOR_RHO))) == pytest.approx(PRIOR_RHO)


def test_closed_form_kl_gradient_passes_gradcheck():
    from lerobot_pacdp.bayesian_layers import _GaussianKL

    torch.manual_seed(5)
    mu = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    sigma = (torch.rand(6, 3, dtype=torch.float64) + 0.1).requires_grad_()
    prior_mu, prior_sigma = torch.randn(6, 3, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m, s: _GaussianKL.apply(m, s, prior_mu, prior_sigma), (mu, sigma))



def _two_layer_block() -> nn.Sequential:
    """Two Bayesian convs: the second one's gradient depends on the first one's weights."""
    torch.manual_seed(6)
    block = nn.Sequential(nn.Conv1d(3, 4, 3, padding=1), nn.Mish(), nn.Conv1d(4, 2, 3, padding=1))
    bayesianize(block, PRIOR_RHO)
    with torch.no_grad():
        for name, param in block.named_parameters():
            if name.endswith("_rho"):
                param.fill_(-1.0)
    return block


def _gradients(block: nn.Sequential, loss: torch.Tensor) -> list[torch.Tensor]:
    block.zero_grad()
    loss.backward()
    return [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in block.parameters()]


@pytest.mark.parametrize("use_checkpoint", [False, True])
def test_a_checkpointed_pass_recomputed_after_the_block_uses_the_same_weight_sample(use_checkpoint):
    block, x = _two_layer_block(), torch.randn(2, 3, 8)
    run = (lambda inp: checkpoint(block, inp, use_reentrant=False)) if use_checkpoint else block
    torch.manual_seed(7)
    with sampled_weights(block):
        loss = run(x).square().sum()
    gradients = _gradients(block, loss)  # after the block: a checkpointed pass is recomputed here
    torch.manual_seed(7)
    with sampled_weights(block):
        reference = _gradients(block, block(x).square().sum())  # the same sample, backward inside the block
    on_mu = _gradients(block, block(x).square().sum())
    assert all(torch.equal(a, b) for a, b in zip(gradients, reference, strict=True))
    assert not torch.allclose(reference[2], on_mu[2])  # the second conv's gradient does depend on the sample


def test_a_checkpointed_pass_on_mu_after_a_sampled_one_is_recomputed_with_mu():
    block, x = _two_layer_block(), torch.randn(2, 3, 8)
    with sampled_weights(block):
        _gradients(block, block(x).square().sum())
    checkpointed = _gradients(block, checkpoint(block, x, use_reentrant=False).square().sum())
    assert all(torch.equal(a, b) for a, b in zip(checkpointed, _gradients(block, block(x).square().sum()), strict=True))


def test_sample_and_kl_share_one_backward_that_passes_gradcheck():
    from lerobot_pacdp.bayesian_layers import _SampleWithKL

    torch.manual_seed(8)
    mu = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    rho = (torch.randn(5, 3, dtype=torch.float64) - 2).requires_grad_()
    xi, prior_mu = torch.randn(5, 3, dtype=torch.float64), torch.randn(5, 3, dtype=torch.float64)
    prior_sigma = torch.tensor(0.3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m, r: _SampleWithKL.apply(m, r, xi, prior_mu, prior_sigma)[:2], (mu, rho))
    sample, kl, sigma = _SampleWithKL.apply(mu, rho, xi, prior_mu, prior_sigma)
    assert torch.equal(sigma, nn.functional.softplus(rho)) and not sigma.requires_grad
    assert torch.allclose(sample, mu + sigma * xi)


def test_the_kl_drawn_with_a_training_sample_is_the_posteriors_kl_with_the_same_gradients():
    torch.manual_seed(9)
    layer = make_bayesian(nn.Conv1d(3, 4, 3, padding=1), PRIOR_RHO)
    _perturb(layer)
    outside = kl_divergence(layer)
    outside.backward()
    expected = [layer.weight.grad.clone(), layer.weight_rho.grad.clone(), layer.bias_rho.grad.clone()]
    layer.zero_grad()
    with sampled_weights(layer):
        inside = kl_divergence(layer)
        with torch.no_grad():
            assert not kl_divergence(layer).requires_grad
    assert inside.dtype == torch.float64 and inside.item() == pytest.approx(outside.item(), rel=1e-6)
    inside.backward()
    got = [layer.weight.grad, layer.weight_rho.grad, layer.bias_rho.grad]
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-8) for a, b in zip(got, expected, strict=True))


def test_sampling_without_gradients_reuses_sigma_until_rho_changes():
    layer = make_bayesian(nn.Linear(6, 5), PRIOR_RHO)
    with torch.no_grad():
        with sampled_weights(layer):
            first = layer.posterior_sigma("weight")
        with sampled_weights(layer):
            assert layer.posterior_sigma("weight") is first  # the same rho: no new softplus
        layer.weight_rho.add_(1.0)  # an optimizer or EMA step changes rho in place
        with sampled_weights(layer):
            assert torch.equal(layer.posterior_sigma("weight"), nn.functional.softplus(layer.weight_rho))
        layer.weight_rho = nn.Parameter(torch.full((5, 6), -1.0))  # a replaced rho, e.g. moved to a device
        with sampled_weights(layer):
            assert torch.equal(layer.posterior_sigma("weight"), nn.functional.softplus(torch.full((5, 6), -1.0)))


def test_a_network_copies_after_a_training_pass_without_its_pending_sample():
    import copy

    layer = make_bayesian(nn.Linear(3, 2), PRIOR_RHO)
    with sampled_weights(layer):
        loss = layer(torch.randn(4, 3)).sum()
    copied = copy.deepcopy(layer)  # the original still holds the sample its backward may recompute with
    loss.backward()
    assert copied._graph_sample.sample is None and copied.current("weight") is copied.weight


def test_bayesian_layers_compile_without_graph_breaks_and_keep_their_gradients():
    block, x = _two_layer_block(), torch.randn(2, 3, 8)
    compiled = torch.compile(block, backend="aot_eager", fullgraph=True)  # fullgraph: a graph break is an error
    torch.manual_seed(10)
    with sampled_weights(block):
        sampled = _gradients(block, compiled(x).square().sum())
    torch.manual_seed(10)
    with sampled_weights(block):
        reference = _gradients(block, block(x).square().sum())
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-7) for a, b in zip(sampled, reference, strict=True))
    assert torch.allclose(compiled(x), block(x))  # and outside a block, on mu


def test_a_draw_over_layers_with_different_priors_has_their_summed_kl_and_sees_a_changed_prior():
    torch.manual_seed(11)
    block = nn.Sequential(nn.Linear(4, 3), nn.Mish(), nn.Linear(3, 2))
    make_bayesian(block[0], PRIOR_RHO)
    make_bayesian(block[2], -2.0)
    for layer in (block[0], block[2]):
        _perturb(layer)
    expected = block[0].kl_divergence() + block[2].kl_divergence()
    with sampled_weights(block):
        inside = kl_divergence(block)
    assert inside.item() == pytest.approx(expected.item(), rel=1e-6)
    with torch.no_grad():
        block[2].weight_prior_mu.add_(0.5)  # a changed prior (e.g. loaded): the cached flat copy is remade
        block[2].prior_rho.fill_(PRIOR_RHO)
    with sampled_weights(block):
        changed = kl_divergence(block)
    assert changed.item() == pytest.approx((block[0].kl_divergence() + block[2].kl_divergence()).item(), rel=1e-6)
    assert changed.item() != pytest.approx(inside.item(), rel=1e-3)
