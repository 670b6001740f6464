"""PAC-DP policy: LeRobot's DiffusionPolicy with a Bayesian U-Net trained on paper Eq. 9.

Everything but the noise-prediction network and the loss is inherited: observation queues, the
observation encoders (deterministic), the DDIM sampler, the processors and the hub/checkpoint code.
"""

import contextlib
import logging
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.utils.device_utils import resolve_safetensors_device
from safetensors.torch import load_model as load_model_as_safetensor
from torch import Tensor

from lerobot_pacdp.bayesian_layers import (
    bayesianize,
    kl_divergence,
    mean_posterior_sigma,
    rho_parameters,
    sampled_weights,
)
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.objective import pac_bayes_objective
from lerobot_pacdp.training_set import training_set_size

logger = logging.getLogger(__name__)

_BAYESIAN_KEY_SUFFIXES = ("_rho", "_prior_mu", "prior_rho")


class CheckpointMismatchError(RuntimeError):
    """A checkpoint's tensors do not match the PAC-DP network they are loaded into."""


def is_conditioning_projection(layer_name: str) -> bool:
    """True for the FiLM projections of the global condition (the paper's "conditional projection layers")."""
    return ".cond_encoder." in f".{layer_name}."


class PacdpPolicy(DiffusionPolicy):
    """Diffusion policy whose U-Net weights follow a factorized Gaussian posterior Q (paper Sec. III)."""

    config_class = PacdpConfig
    name = "pacdp"

    def __init__(self, config: PacdpConfig, dataset_meta: Any | None = None, **kwargs):
        super().__init__(config, **kwargs)
        self.config: PacdpConfig
        keep_deterministic = (lambda name: False) if config.bayesian_conditioning else is_conditioning_projection
        self.bayesian_layer_names = bayesianize(self.diffusion.unet, config.prior_rho, keep_deterministic)
        if config.num_train_samples is None and dataset_meta is not None:
            size = training_set_size(dataset_meta)
            config.num_train_samples = size.num_frames
            logger.info(
                "PAC-DP: N = %d training samples (%d episodes, from the %s).",
                size.num_frames,
                size.num_episodes,
                size.source,
            )

    @property
    def unet(self) -> torch.nn.Module:
        return self.diffusion.unet

    def get_optim_params(self) -> list[dict]:
        """Two groups: rho gets no weight decay (decay would pull sigma towards softplus(0))."""
        rho = rho_parameters(self.unet)
        rho_ids = {id(p) for p in rho}
        others = [p for p in self.diffusion.parameters() if id(p) not in rho_ids]
        return [{"params": others}, {"params": rho, "weight_decay": 0.0}]

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Training: Eq. 9 with one weight sample. Eval: the posterior mean's denoising error (held-out NPE)."""
        if not self.training:
            npe, _ = super().forward(batch)
            return npe, {"denoise_loss": npe.item()}

        num_samples = self.config.num_train_samples
        if num_samples is None:
            raise ValueError(
                "PAC-DP needs N (`num_train_samples`) to train, and no dataset was given to derive it. "
                "Pass --policy.num_train_samples=<number of training frames>."
            )
        with sampled_weights(self.unet):  # one weight sample for this forward pass
            risk, _ = super().forward(batch)
            with torch.set_grad_enabled(self.config.kl_weight > 0):
                kl = kl_divergence(self.unet)
            sigma_mean = mean_posterior_sigma(self.unet)
        objective = pac_bayes_objective(risk, kl, num_samples, self.config.delta, self.config.kl_weight)
        return objective.total, {
            "denoise_loss": risk.item(),
            "kl": kl.item(),
            "bound_sqrt_term": objective.sqrt_term.item(),
            "bound_linear_term": objective.linear_term.item(),
            "sigma_mean": sigma_mean,
        }

    def inference_weights(self, generator: torch.Generator | None = None) -> contextlib.AbstractContextManager:
        """The weights one action chunk is generated with (paper Algorithm 2)."""
        if self.config.inference_mode == "sample":
            return sampled_weights(self.unet, generator)
        return contextlib.nullcontext()

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        with self.inference_weights():
            return super().predict_action_chunk(batch, noise=noise)

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Load strictly: LeRobot only warns on missing keys, which would silently drop a posterior."""
        missing, unexpected = load_model_as_safetensor(
            model, model_file, strict=False, device=resolve_safetensors_device(map_location)
        )
        if missing or unexpected:
            bayesian = [k for k in (*missing, *unexpected) if k.endswith(_BAYESIAN_KEY_SUFFIXES)]
            raise CheckpointMismatchError(
                f"{Path(model_file)} does not match this PAC-DP network: "
                f"{len(missing)} missing keys {sorted(missing)[:6]}, {len(unexpected)} unexpected keys "
                f"{sorted(unexpected)[:6]} ({len(bayesian)} of them Bayesian mu/rho/prior tensors). "
                "Was it saved by a different policy type, or with a different `bayesian_conditioning` "
                "or U-Net size? Load it with the config.json saved beside it."
            )
        return model
