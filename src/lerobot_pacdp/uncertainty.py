"""Posterior uncertainty of an action chunk: how much chunks from different posterior weight samples disagree.

For one decision step, K weight samples w_k ~ Q generate K chunks from the *same* initial noise (the noise
the acting chunk was generated from), so with DDIM (deterministic given its initial noise) they differ only
through the weights. The uncertainty is

    u = sqrt( mean over executed steps t and action dims d of Var_k[a_k,t,d] )     (Var with K - 1)

in normalised action units (the U-Net's output space, min-max scaled to [-1, 1]): every action dimension
then spans the same range, so none dominates by its physical units, and u is the RMS distance of one
sample's executed action from the samples' mean. Only the `n_action_steps` actions the policy executes
enter; the rest of the horizon is replanned before it is used.

The baseline any diffusion policy has is the same spread over K *initial noises* with fixed weights (the
posterior mean, or the DP twin's weights). Both are computed in one batched sampler call each: the K
noises as K x B rows of LeRobot's own sampler, the K weight samples as one pass over K stacked weight sets
(`torch.func.functional_call` under `torch.func.vmap`) that stands in for the U-Net inside that sampler.
Every draw comes from the caller's generator, never the global RNG, so the actions a policy takes with the
uncertainty on are exactly those it takes with it off.
"""

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel
from lerobot.policies.utils import get_device_from_parameters, get_dtype_from_parameters
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from lerobot_pacdp.bayesian_layers import BayesianLayer
from lerobot_pacdp.module_swaps import child_replaced

DEFAULT_SAMPLES = 8
_SEED_OFFSET = 0x5EED  # the policy's uncertainty generator starts at torch's initial seed plus this


@dataclass(frozen=True)
class ChunkUncertainty:
    """One decision step of a batch of B environments.

    actions: (B, n_action_steps, action_dim) the chunk the policy acts with, normalised (as
        `predict_action_chunk` returns it).
    posterior: (B,) spread of the chunks of K posterior weight samples from the acting chunk's initial
        noise; None for a policy without a posterior (the DP twin).
    noise: (B,) spread of the chunks of K initial noises with the posterior-mean (fixed) weights.
    """

    actions: Tensor
    posterior: Tensor | None
    noise: Tensor


def action_spread(chunks: Tensor) -> Tensor:
    """(K, B, T, D) chunks -> (B,) sqrt of the across-sample variance averaged over steps and dims."""
    return chunks.var(dim=0, correction=1).mean(dim=(1, 2)).sqrt()


def uncertainty_generator(device: torch.device) -> torch.Generator:
    """A generator for the uncertainty's draws, reproducible under a seeded run (`--seed`) and apart from
    the global stream the actions are drawn from."""
    return torch.Generator(device=device).manual_seed(torch.initial_seed() + _SEED_OFFSET)


def posterior_weight_samples(unet: nn.Module, num_samples: int, generator: torch.Generator) -> dict[str, Tensor]:
    """K draws w = mu + sigma * xi (paper Eq. 6) of every Bayesian tensor, stacked: {qualified name: (K, ...)}."""
    samples = {}
    for layer_name, layer in unet.named_modules():
        if not isinstance(layer, BayesianLayer):
            continue
        for rho_name, _ in layer.named_parameters(recurse=False):
            if not rho_name.endswith("_rho"):
                continue
            name = rho_name.removesuffix("_rho")
            mu = getattr(layer, name)
            xi = torch.randn((num_samples, *mu.shape), generator=generator, dtype=mu.dtype, device=mu.device)
            samples[f"{layer_name}.{name}" if layer_name else name] = torch.addcmul(mu, layer.posterior_sigma(name), xi)
    return samples


class _UnetPerWeightSet(nn.Module):
    """Stands in for the U-Net inside LeRobot's sampler: rows k*B .. k*B + B - 1 of a K*B batch are denoised
    with weight set k, all K in one vmapped pass (the Bayesian layers read `weight`/`bias`, which
    `functional_call` substitutes, whenever no sample is drawn)."""

    def __init__(self, unet: nn.Module, weight_sets: dict[str, Tensor]):
        super().__init__()
        self.unet = unet
        self.weight_sets = weight_sets
        self.num_sets = next(iter(weight_sets.values())).shape[0]

    def forward(self, x: Tensor, timestep: Tensor, global_cond: Tensor) -> Tensor:
        batch = x.shape[0] // self.num_sets

        def denoise(weights: dict[str, Tensor], sample: Tensor) -> Tensor:
            return torch.func.functional_call(self.unet, weights, (sample, timestep[:batch]), {"global_cond": global_cond[:batch]})

        return torch.func.vmap(denoise)(self.weight_sets, x.unflatten(0, (self.num_sets, batch))).flatten(0, 1)


@contextlib.contextmanager
def _recorded_generation(model: DiffusionModel) -> Iterator[dict[str, object]]:
    """Record the observation window and initial noise LeRobot's `generate_actions` is called with. Where
    LeRobot would draw the noise itself, it is drawn here with `conditional_sample`'s own call, so the RNG
    stream, hence the chunk, is unchanged."""
    recorded: dict[str, object] = {}
    generate = model.generate_actions

    def generate_recording(batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        if noise is None:
            size = (batch[OBS_STATE].shape[0], model.config.horizon, model.config.action_feature.shape[0])
            noise = torch.randn(size=size, dtype=get_dtype_from_parameters(model), device=get_device_from_parameters(model))
        recorded.update(window=batch, noise=noise)
        return generate(batch, noise=noise)

    model.generate_actions = generate_recording
    try:
        yield recorded
    finally:
        del model.generate_actions


def _executed(model: DiffusionModel, chunks: Tensor, num_samples: int) -> Tensor:
    """(K*B, horizon, D) sampler output -> (K, B, n_action_steps, D), the slice `generate_actions` keeps."""
    start = model.config.n_obs_steps - 1
    return chunks[:, start : start + model.config.n_action_steps].unflatten(0, (num_samples, -1))


def posterior_chunks(
    model: DiffusionModel, global_cond: Tensor, noise: Tensor, num_samples: int, generator: torch.Generator
) -> Tensor | None:
    """The executed chunks (K, B, n_action_steps, D) of K posterior weight samples, all from `noise` (B, horizon,
    D), in one vmapped pass; None for a network without Bayesian layers."""
    weight_sets = posterior_weight_samples(model.unet, num_samples, generator)
    if not weight_sets:
        return None
    rows = num_samples * noise.shape[0]
    with child_replaced(model, "unet", _UnetPerWeightSet(model.unet, weight_sets)):
        chunks = model.conditional_sample(rows, global_cond.repeat(num_samples, 1), generator, noise.repeat(num_samples, 1, 1))
    return _executed(model, chunks, num_samples)


def noise_chunks(
    model: DiffusionModel, global_cond: Tensor, noise_like: Tensor, num_samples: int, generator: torch.Generator
) -> Tensor:
    """The executed chunks (K, B, n_action_steps, D) of K initial noises with the network's fixed weights."""
    rows = num_samples * noise_like.shape[0]
    noises = torch.randn((rows, *noise_like.shape[1:]), generator=generator, dtype=noise_like.dtype, device=noise_like.device)
    chunks = model.conditional_sample(rows, global_cond.repeat(num_samples, 1), generator, noises)
    return _executed(model, chunks, num_samples)


def chunk_with_uncertainty(
    model: DiffusionModel, act: Callable[[], Tensor], num_samples: int, generator: torch.Generator
) -> ChunkUncertainty:
    """Run `act` (the policy's own chunk generation through `model`) and measure the chunk's uncertainty.

    `act` must leave no weight sample drawn behind it: the K weight sets replace mu, not a sample.
    """
    if num_samples < 2:
        raise ValueError(f"the spread of action chunks needs at least 2 samples, got {num_samples}.")
    with _recorded_generation(model) as recorded:
        actions = act()
    noise = recorded["noise"]
    global_cond = model._prepare_global_conditioning(recorded["window"])
    posterior = posterior_chunks(model, global_cond, noise, num_samples, generator)
    return ChunkUncertainty(
        actions=actions,
        posterior=None if posterior is None else action_spread(posterior),
        noise=action_spread(noise_chunks(model, global_cond, noise, num_samples, generator)),
    )
