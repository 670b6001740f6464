"""Factorized-Gaussian Bayesian versions of Linear, Conv1d and ConvTranspose1d (paper Sec. III-B).

An existing layer is converted in place (its class is swapped for a Bayesian subclass), so LeRobot's
U-Net code runs unchanged and a converted network keeps the deterministic layer's parameter names:

- `weight` / `bias` hold the posterior mean mu. A PAC-DP checkpoint therefore loads into a plain
  diffusion policy (the extra keys aside), and mean-mode inference is exactly that network.
- `weight_rho` / `bias_rho` hold rho; the posterior std is sigma = softplus(rho) (Eq. 7).
- `weight_prior_mu` / `bias_prior_mu` (buffers) hold the prior mean, and `prior_rho` (a 0-d buffer)
  the prior's constant rho, so the exact KL can be recomputed from a checkpoint alone.

Prior (following Perez-Ortiz et al. 2021 / Biggs & Guedj 2023, as the paper does): weight means are
drawn from N(0, 1/n_in) truncated at +-2 std, with n_in = in_channels/groups * kernel_size for both
convolution kinds (the inputs that feed one output through the kernel; a layer and its transpose
share a scale) and in_features for Linear. Bias means are 0. Every prior std is softplus(prior_rho).
The posterior starts equal to the prior (mu = prior mean, rho = prior_rho), so KL(Q||P) is exactly 0
at step 0. Biases are Bayesian exactly like weights (own mu, rho, prior) and enter the KL the same way.

Sampling is explicit: outside `sampled_weights(...)` every layer uses mu (zero sampling cost); inside
it, each layer uses one weight sample drawn on entry (Eq. 6), shared by every call in the block. That
gives one sample per training forward pass and one per generated action chunk, never one per
denoising step. A pass that the autograd engine re-runs during backward (gradient checkpointing's
recomputation, after the block has exited) uses the weights the original pass used: the sample of the
most recent forward pass run with gradients, or mu if that pass ran on mu.
"""

import contextlib
import copy
import math
from collections.abc import Callable, Iterator

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

_PARAM_NAMES = ("weight", "bias")


def softplus_inverse(sigma: float) -> float:
    """rho such that softplus(rho) = sigma (Eq. 7 inverted)."""
    return math.log(math.expm1(sigma))


def _in_backward_pass() -> bool:
    """True while the autograd engine runs a backward pass (where checkpointed segments are recomputed)."""
    return torch._C._current_graph_task_id() != -1


def _kl_terms_sum(mu: Tensor, sigma: Tensor, prior_mu: Tensor, prior_sigma: Tensor) -> Tensor:
    """sum KL(N(mu, sigma^2) || N(mu_p, sp^2)) over elements, in the inputs' dtype.

    With r = sigma / sp, each element is -log r + (r^2 - 1) / 2 + (mu - mu_p)^2 / (2 sp^2): every part is
    exactly 0 where Q = P and each element is >= 0, so the sum has no cancellation (8 passes, one log).
    """
    ratio = sigma / prior_sigma
    terms = torch.addcmul(ratio.new_full((), -0.5), ratio, ratio, value=0.5)
    terms.sub_(ratio.log_())
    scaled_gap = torch.sub(mu, prior_mu).div_(prior_sigma * math.sqrt(2.0))
    terms.addcmul_(scaled_gap, scaled_gap)
    return terms.sum()


def _kl_gradients(
    grad_kl: Tensor, mu: Tensor, sigma: Tensor, prior_mu: Tensor, prior_sigma: Tensor, grad_sigma: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """grad_kl * dKL/dmu = grad_kl (mu - mu_p) / sp^2 and grad_kl * dKL/dsigma = grad_kl (sigma / sp^2 - 1 / sigma),
    the latter added into `grad_sigma` in place when given."""
    scale = grad_kl.to(sigma.dtype)
    scaled_inv_var = scale / prior_sigma.square()
    grad_mu = torch.sub(mu, prior_mu).mul_(scaled_inv_var)
    if grad_sigma is None:
        grad_sigma = torch.mul(sigma, scaled_inv_var)
    else:
        grad_sigma.addcmul_(sigma, scaled_inv_var)
    return grad_mu, grad_sigma.addcdiv_(scale.expand_as(sigma), sigma, value=-1.0)


class _GaussianKL(torch.autograd.Function):
    """The KL of `_kl_terms_sum` with its closed-form gradient, for a posterior given by (mu, sigma).

    The analytic backward replaces the ~10 autograd nodes per tensor the expression would record and saves
    no tensor of its own.
    """

    @staticmethod
    def forward(ctx, mu: Tensor, sigma: Tensor, prior_mu: Tensor, prior_sigma: Tensor) -> Tensor:
        ctx.save_for_backward(mu, sigma, prior_mu, prior_sigma)
        return _kl_terms_sum(mu, sigma, prior_mu, prior_sigma)

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        mu, sigma, prior_mu, prior_sigma = ctx.saved_tensors
        grad_mu, grad_sigma = _kl_gradients(grad_output, mu, sigma, prior_mu, prior_sigma)
        return grad_mu, grad_sigma, None, None


class _SampleWithKL(torch.autograd.Function):
    """One training draw of a tensor: w = mu + softplus(rho) * xi (Eq. 6) and the KL of the posterior it came from.

    Sample and KL share one backward, so their gradients reach mu and rho without the separate passes autograd
    would make (softplus, addcmul, KL, then sums of the two contributions). Only xi is saved: sigma is
    recomputed in backward, which keeps one tensor per weight less alive between forward and backward.
    Outputs: w, the KL (a 0-d tensor of mu's dtype) and sigma (not differentiable; for logging and the KL).
    """

    @staticmethod
    def forward(ctx, mu: Tensor, rho: Tensor, xi: Tensor, prior_mu: Tensor, prior_sigma: Tensor):
        sigma = F.softplus(rho)
        sample = torch.addcmul(mu, sigma, xi)
        kl = _kl_terms_sum(mu, sigma, prior_mu, prior_sigma)
        ctx.save_for_backward(mu, rho, xi, prior_mu, prior_sigma)
        ctx.mark_non_differentiable(sigma)
        ctx.set_materialize_grads(False)
        return sample, kl, sigma

    @staticmethod
    def backward(ctx, grad_sample: Tensor | None, grad_kl: Tensor | None, _grad_sigma: None):
        mu, rho, xi, prior_mu, prior_sigma = ctx.saved_tensors
        grad_sigma = grad_sample * xi if grad_sample is not None else torch.zeros_like(xi)
        grad_mu = grad_sample
        if grad_kl is not None:
            kl_grad_mu, grad_sigma = _kl_gradients(grad_kl, mu, F.softplus(rho), prior_mu, prior_sigma, grad_sigma)
            grad_mu = kl_grad_mu if grad_mu is None else kl_grad_mu.add_(grad_mu)
        return grad_mu, grad_sigma.mul_(torch.sigmoid(rho)), None, None, None


class _PendingSample:
    """The weight sample a backward recomputation must see. A copy of the network starts without one: a deep
    copy or a pickle has no pending backward (and a sample with an autograd history cannot be copied)."""

    def __init__(self, sample: dict[str, Tensor] | None = None):
        self.sample = sample

    def __deepcopy__(self, memo) -> "_PendingSample":
        return _PendingSample()

    def __reduce__(self):
        return (_PendingSample, ())


class BayesianLayer(nn.Module):
    """Mixin behaviour shared by the Bayesian layer classes; never instantiated directly."""

    weight_rho: nn.Parameter
    weight_prior_mu: Tensor
    prior_rho: Tensor
    _sampled: dict[str, Tensor] | None
    _sampled_sigma: dict[str, Tensor] | None
    _sampled_kl: Tensor | None
    _graph_sample: _PendingSample
    _sigma_cache: dict[str, tuple[Tensor, int, Tensor]]

    def _init_bayesian(self, prior_rho: float, fan_in: int) -> None:
        """Turn the deterministic parameters into (mu, rho) and record the prior (Q = P at init)."""
        prior_std = 1.0 / math.sqrt(fan_in)
        self.register_buffer("prior_rho", torch.tensor(float(prior_rho), dtype=self.weight.dtype))
        for name in self._bayesian_param_names():
            mu: nn.Parameter = getattr(self, name)
            with torch.no_grad():
                prior_mu = torch.zeros_like(mu)
                if name == "weight":
                    nn.init.trunc_normal_(prior_mu, 0.0, prior_std, -2 * prior_std, 2 * prior_std)
                mu.copy_(prior_mu)
            self.register_buffer(f"{name}_prior_mu", prior_mu)
            self.register_parameter(f"{name}_rho", nn.Parameter(torch.full_like(mu, float(prior_rho))))
        self._graph_sample = _PendingSample()
        self._sigma_cache = {}
        self.clear_sample()

    def _bayesian_param_names(self) -> tuple[str, ...]:
        return tuple(name for name in _PARAM_NAMES if getattr(self, name, None) is not None)

    def posterior_sigma(self, name: str = "weight") -> Tensor:
        """sigma = softplus(rho) (Eq. 7); inside a sampling block, the value computed for the sample."""
        if self._sampled_sigma is not None:
            return self._sampled_sigma[name]
        return F.softplus(getattr(self, f"{name}_rho"))

    def _sigma_without_gradients(self, name: str) -> Tensor:
        """softplus(rho) for a draw without gradients, reused while rho is unchanged: one softplus per new rho,
        not per action chunk. The cache keeps rho's storage alive, so a replaced rho cannot reuse its address."""
        rho = getattr(self, f"{name}_rho")
        cached = self._sigma_cache.get(name)
        if cached is not None and cached[0].data_ptr() == rho.data_ptr() and cached[1] == rho._version:
            return cached[2]
        sigma = F.softplus(rho.detach())
        self._sigma_cache[name] = (rho.detach(), rho._version, sigma)
        return sigma

    def draw_sample(self, generator: torch.Generator | None = None) -> None:
        """Draw w = mu + softplus(rho) * xi, xi ~ N(0, I) (Eq. 6), for every Bayesian parameter.

        sigma is kept until `clear_sample` so the KL and the logging of the same step reuse it; with gradients
        the KL is computed with the sample (`_SampleWithKL`) and `kl_divergence` returns it.
        """
        grad = torch.is_grad_enabled()
        if grad:
            self._graph_sample.sample = None  # the previous graph's sample is not kept alive beside the new one
        prior_sigma = F.softplus(self.prior_rho)
        sample, sigmas, kls = {}, {}, []
        for name in self._bayesian_param_names():
            mu, rho = getattr(self, name), getattr(self, f"{name}_rho")
            xi = torch.randn(mu.shape, dtype=mu.dtype, device=mu.device, generator=generator)
            if grad and (mu.requires_grad or rho.requires_grad):
                prior_mu = getattr(self, f"{name}_prior_mu")
                sample[name], kl, sigmas[name] = _SampleWithKL.apply(mu, rho, xi, prior_mu, prior_sigma)
                kls.append(kl.double())
            else:
                sigmas[name] = self._sigma_without_gradients(name)
                sample[name] = torch.addcmul(mu, sigmas[name], xi)
        self._sampled, self._sampled_sigma = sample, sigmas
        self._sampled_kl = torch.stack(kls).sum() if len(kls) == len(sample) else None

    def clear_sample(self) -> None:
        """End the sampling block: new passes use mu (a backward recomputation still sees its own weights)."""
        self._sampled = None
        self._sampled_sigma = None
        self._sampled_kl = None

    def current(self, name: str) -> Tensor | None:
        """The tensor this forward pass uses: the drawn sample if any, else the posterior mean.

        A pass re-run during backward (gradient checkpointing) gets what the last pass with gradients got.
        A compiled graph takes the weights as inputs and its own backward recomputes with them.
        """
        if torch.compiler.is_compiling():
            sample = self._sampled
        elif _in_backward_pass():
            sample = self._graph_sample.sample
        else:
            sample = self._sampled
            if torch.is_grad_enabled():
                self._graph_sample.sample = sample
        if sample is not None and name in sample:
            return sample[name]
        return getattr(self, name)

    def kl_divergence(self) -> Tensor:
        """Closed-form KL(Q||P) between factorized Gaussians, summed over all elements (Eq. 12 terms).

        KL = sum 0.5 * (log(sp^2/sq^2) + (sq^2 + (mq - mp)^2) / sp^2 - 1): each tensor's nonnegative
        terms summed in its dtype, the tensors' sums added in float64 (see `_kl_terms_sum`). Inside a
        sampling block drawn with gradients, the KL computed with the sample (the same value).
        """
        if self._sampled_kl is not None:
            return self._sampled_kl if torch.is_grad_enabled() else self._sampled_kl.detach()
        prior_sigma = F.softplus(self.prior_rho)
        total = torch.zeros((), dtype=torch.float64, device=self.prior_rho.device)
        for name in self._bayesian_param_names():
            rho = getattr(self, f"{name}_rho")
            sigma = F.softplus(rho) if torch.is_grad_enabled() and rho.requires_grad else self.posterior_sigma(name)
            total = total + _GaussianKL.apply(getattr(self, name), sigma, getattr(self, f"{name}_prior_mu"), prior_sigma).double()
        return total

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, bayesian(prior_sigma={F.softplus(self.prior_rho).item():.4g})"


class BayesianLinear(BayesianLayer, nn.Linear):
    def forward(self, x: Tensor) -> Tensor:
        return F.linear(x, self.current("weight"), self.current("bias"))


class BayesianConv1d(BayesianLayer, nn.Conv1d):
    def forward(self, x: Tensor) -> Tensor:
        return self._conv_forward(x, self.current("weight"), self.current("bias"))


class BayesianConvTranspose1d(BayesianLayer, nn.ConvTranspose1d):
    def forward(self, x: Tensor, output_size: list[int] | None = None) -> Tensor:
        output_padding = self._output_padding(
            x, output_size, self.stride, self.padding, self.kernel_size, 1, self.dilation
        )
        return F.conv_transpose1d(
            x,
            self.current("weight"),
            self.current("bias"),
            self.stride,
            self.padding,
            output_padding,
            self.groups,
            self.dilation,
        )


_BAYESIAN_CLASS: dict[type[nn.Module], type[BayesianLayer]] = {
    nn.Linear: BayesianLinear,
    nn.Conv1d: BayesianConv1d,
    nn.ConvTranspose1d: BayesianConvTranspose1d,
}


def _fan_in(layer: nn.Module) -> int:
    if isinstance(layer, nn.Linear):
        return layer.in_features
    return layer.in_channels // layer.groups * layer.kernel_size[0]


def make_bayesian(layer: nn.Module, prior_rho: float) -> BayesianLayer:
    """Convert one Linear/Conv1d/ConvTranspose1d to its Bayesian version in place and return it."""
    bayesian_cls = _BAYESIAN_CLASS.get(type(layer))
    if bayesian_cls is None:
        raise TypeError(f"No Bayesian version of {type(layer).__name__}; supported: Linear, Conv1d, ConvTranspose1d")
    layer.__class__ = bayesian_cls
    layer._init_bayesian(prior_rho, _fan_in(layer))
    return layer


def bayesianize(
    network: nn.Module, prior_rho: float, keep_deterministic: Callable[[str], bool] = lambda name: False
) -> list[str]:
    """Make every Linear/Conv1d/ConvTranspose1d of `network` Bayesian, except names `keep_deterministic` selects.

    Returns the qualified names of the converted layers.
    """
    converted = []
    for name, module in list(network.named_modules()):
        if type(module) in _BAYESIAN_CLASS and not keep_deterministic(name):
            make_bayesian(module, prior_rho)
            converted.append(name)
    return converted


def bayesian_layers(network: nn.Module) -> Iterator[BayesianLayer]:
    return (m for m in network.modules() if isinstance(m, BayesianLayer))


def kl_divergence(network: nn.Module) -> Tensor:
    """KL(Q||P) of the whole network: the sum of its layers' KLs (paper Eq. 12), float64."""
    terms = [layer.kl_divergence() for layer in bayesian_layers(network)]
    if not terms:
        raise ValueError("The network has no Bayesian layers, so KL(Q||P) is undefined.")
    return torch.stack(terms).sum()


def exact_kl(network: nn.Module) -> float:
    """KL(Q||P) from the saved mu, rho and prior tensors, with float64 elementwise terms (on a float64 copy):
    training's float32 terms are rounded at ~1e-7 relative each, enough to turn a KL of 0 slightly negative."""
    return kl_divergence(copy.deepcopy(network).double()).item()


def rho_parameters(network: nn.Module) -> list[nn.Parameter]:
    return [p for layer in bayesian_layers(network) for n, p in layer.named_parameters(recurse=False) if n.endswith("_rho")]


@torch.no_grad()
def mean_posterior_sigma(network: nn.Module) -> float:
    """Element-weighted mean posterior std over all Bayesian parameters (a training-health signal); one
    host sync, not one per layer."""
    sigmas = [layer.posterior_sigma(name) for layer in bayesian_layers(network) for name in layer._bayesian_param_names()]
    if not sigmas:
        return 0.0
    total = torch.stack([s.sum() for s in sigmas]).double().sum()
    return total.item() / sum(s.numel() for s in sigmas)


@contextlib.contextmanager
def sampled_weights(network: nn.Module, generator: torch.Generator | None = None) -> Iterator[None]:
    """Within the block, every Bayesian layer uses one weight sample drawn on entry (Eq. 6)."""
    layers = list(bayesian_layers(network))
    for layer in layers:
        layer.draw_sample(generator)
    try:
        yield
    finally:
        for layer in layers:
            layer.clear_sample()
