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
denoising step.
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


class _GaussianKL(torch.autograd.Function):
    """sum KL(N(mu, sigma^2) || N(mu_p, sp^2)) over elements, with its closed-form gradient.

    Autograd would record ~8 elementwise nodes over every parameter; the analytic backward is two
    passes: dKL/dmu = (mu - mu_p) / sp^2 and dKL/dsigma = sigma / sp^2 - 1 / sigma.
    Elementwise: (log sp - log sigma) + ((sigma^2 + (mu - mu_p)^2) / (2 sp^2) - 1/2), exactly 0 at Q = P.
    """

    @staticmethod
    def forward(ctx, mu: Tensor, sigma: Tensor, prior_mu: Tensor, prior_sigma: Tensor) -> Tensor:
        gap = mu - prior_mu
        prior_var = prior_sigma.square()
        elementwise = (torch.log(prior_sigma) - torch.log(sigma)) + (
            (sigma.square() + gap.square()) / (2 * prior_var) - 0.5
        )
        ctx.save_for_backward(gap, sigma, prior_var)
        return elementwise.sum(dtype=torch.float64)

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        gap, sigma, prior_var = ctx.saved_tensors
        scale = grad_output.to(sigma.dtype)
        grad_mu = gap * (scale / prior_var) if ctx.needs_input_grad[0] else None
        grad_sigma = (sigma / prior_var - sigma.reciprocal()) * scale if ctx.needs_input_grad[1] else None
        return grad_mu, grad_sigma, None, None


class BayesianLayer(nn.Module):
    """Mixin behaviour shared by the Bayesian layer classes; never instantiated directly."""

    weight_rho: nn.Parameter
    weight_prior_mu: Tensor
    prior_rho: Tensor
    _sampled: dict[str, Tensor] | None
    _sampled_sigma: dict[str, Tensor] | None

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
        self.clear_sample()

    def _bayesian_param_names(self) -> tuple[str, ...]:
        return tuple(name for name in _PARAM_NAMES if getattr(self, name, None) is not None)

    def posterior_sigma(self, name: str = "weight") -> Tensor:
        """sigma = softplus(rho) (Eq. 7); inside a sampling block, the value computed for the sample."""
        if self._sampled_sigma is not None:
            return self._sampled_sigma[name]
        return F.softplus(getattr(self, f"{name}_rho"))

    def draw_sample(self, generator: torch.Generator | None = None) -> None:
        """Draw w = mu + softplus(rho) * xi, xi ~ N(0, I) (Eq. 6), for every Bayesian parameter.

        sigma is kept until `clear_sample` so the KL of the same step reuses it (one softplus pass).
        """
        sample, sigmas = {}, {}
        for name in self._bayesian_param_names():
            mu = getattr(self, name)
            sigma = F.softplus(getattr(self, f"{name}_rho"))
            xi = torch.randn(mu.shape, dtype=mu.dtype, device=mu.device, generator=generator)
            sample[name] = torch.addcmul(mu, sigma, xi)
            sigmas[name] = sigma
        self._sampled, self._sampled_sigma = sample, sigmas

    def clear_sample(self) -> None:
        self._sampled = None
        self._sampled_sigma = None

    def current(self, name: str) -> Tensor | None:
        """The tensor used in the forward pass: the drawn sample if any, else the posterior mean."""
        if self._sampled is not None and name in self._sampled:
            return self._sampled[name]
        return getattr(self, name)

    def kl_divergence(self) -> Tensor:
        """Closed-form KL(Q||P) between factorized Gaussians, summed over all elements (Eq. 12 terms).

        KL = sum 0.5 * (log(sp^2/sq^2) + (sq^2 + (mq - mp)^2) / sp^2 - 1), summed in float64
        (see `_GaussianKL` for the exact arithmetic and the gradient).
        """
        prior_sigma = F.softplus(self.prior_rho)
        total = torch.zeros((), dtype=torch.float64, device=self.prior_rho.device)
        for name in self._bayesian_param_names():
            total = total + _GaussianKL.apply(
                getattr(self, name), self.posterior_sigma(name), getattr(self, f"{name}_prior_mu"), prior_sigma
            )
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
    """Element-weighted mean posterior std over all Bayesian parameters (a training-health signal)."""
    sigmas = [layer.posterior_sigma(name) for layer in bayesian_layers(network) for name in layer._bayesian_param_names()]
    return sum(s.sum().item() for s in sigmas) / max(sum(s.numel() for s in sigmas), 1)


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
