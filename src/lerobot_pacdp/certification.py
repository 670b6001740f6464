"""What a sound PAC-Bayes certificate needs besides the posterior: every other trained tensor fixed in advance.

A PAC-Bayes bound holds for predictors whose only data-dependent part is the posterior Q. The diffusion
model's deterministic tensors (the FiLM `cond_encoder` projections unless `bayesian_conditioning`, the
GroupNorm affine parameters, the observation encoders) are outside the KL. With
`PacdpConfig.freeze_deterministic` they are never trained: they keep a *reference* value fixed before any
demonstration is seen, and `pacdp-certify` refuses a checkpoint where they do not hold it.

- Data-free prior: the reference is LeRobot's own initialisation of the diffusion model, drawn on the CPU
  from `REFERENCE_SEED`, so it depends on the configuration alone and is rebuilt at certification time.
- Learned prior (`pacdp-learned-prior`): the reference is the prior checkpoint's tensors (trained on a
  disjoint split), and the checkpoint's prior means and prior rho must be that checkpoint's too.
"""

from dataclasses import dataclass

import torch
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel
from torch import Tensor, nn

from lerobot_pacdp.bayesian_layers import bayesian_layers

REFERENCE_SEED = 0
_PRIOR_SUFFIXES = ("_prior_mu", "prior_rho")


def _bayesian_layer_names(network: nn.Module) -> set[str]:
    layers = set(bayesian_layers(network))
    return {name for name, module in network.named_modules() if module in layers}


def _owner(key: str) -> str:
    return key.rpartition(".")[0]


def deterministic_tensors(network: nn.Module) -> dict[str, Tensor]:
    """Every floating-point parameter and buffer of `network` outside its Bayesian layers, by state-dict key."""
    bayesian = _bayesian_layer_names(network)
    return {
        key: value
        for key, value in network.state_dict().items()
        if value.is_floating_point() and _owner(key) not in bayesian
    }


def prior_tensors(network: nn.Module) -> dict[str, Tensor]:
    """The prior of every Bayesian layer: its `*_prior_mu` buffers and its `prior_rho`, by state-dict key."""
    bayesian = _bayesian_layer_names(network)
    return {
        key: value
        for key, value in network.state_dict().items()
        if _owner(key) in bayesian and key.endswith(_PRIOR_SUFFIXES)
    }


def data_free_reference(config: DiffusionConfig) -> dict[str, Tensor]:
    """LeRobot's initialisation of the diffusion model for `config`, drawn from `REFERENCE_SEED` on the CPU.

    The global RNG is forked, so building the reference leaves the caller's random stream untouched.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(REFERENCE_SEED)
        return DiffusionModel(config).state_dict()


@torch.no_grad()
def freeze_deterministic(network: nn.Module, reference: dict[str, Tensor]) -> list[str]:
    """Set every deterministic tensor of `network` to `reference` and stop its training; returns the keys."""
    targets = deterministic_tensors(network)
    missing = sorted(set(targets) - set(reference))
    if missing:
        raise KeyError(f"the reference has no value for {len(missing)} deterministic tensors, e.g. {missing[:3]}")
    for key, tensor in targets.items():
        tensor.copy_(reference[key])
    for name, parameter in network.named_parameters():
        if name in targets:
            parameter.requires_grad_(False)
    return sorted(targets)


@dataclass(frozen=True)
class TensorDifference:
    """One tensor that is not its reference: `problem` says how (missing, shape, or values)."""

    name: str
    problem: str
    max_abs_difference: float | None = None

    def __str__(self) -> str:
        if self.max_abs_difference is None:
            return f"{self.name} ({self.problem})"
        return f"{self.name} (max |difference| {self.max_abs_difference:.3g})"


def tensor_differences(actual: dict[str, Tensor], reference: dict[str, Tensor]) -> list[TensorDifference]:
    """Every key of `actual` whose tensor is not bitwise its reference, largest difference first."""
    differences = []
    for name, value in actual.items():
        expected = reference.get(name)
        if expected is None:
            differences.append(TensorDifference(name, "not in the reference"))
        elif expected.shape != value.shape:
            differences.append(
                TensorDifference(name, f"shape {tuple(value.shape)}, reference {tuple(expected.shape)}")
            )
        elif not torch.equal(value.cpu(), expected.to("cpu", value.dtype)):
            gap = (value.detach().cpu().double() - expected.cpu().double()).abs().max().item()
            differences.append(TensorDifference(name, "values", gap))
    return sorted(differences, key=lambda d: -(d.max_abs_difference or float("inf")))


def describe_differences(differences: list[TensorDifference], total: int, limit: int = 3) -> str:
    """'3 of 50 tensors differ, e.g. a (max |difference| 0.1), ...' for an error message."""
    shown = ", ".join(str(d) for d in differences[:limit])
    return f"{len(differences)} of {total} tensors differ, e.g. {shown}"
