"""PAC-DP policy: LeRobot's DiffusionPolicy with a Bayesian U-Net trained on paper Eq. 9.

Everything but the noise-prediction network, the loss and the EMA is inherited: observation queues, the
observation encoders (deterministic), the DDIM sampler, the processors and the hub/checkpoint code.

With `use_ema` (the default) the policy holds two copies of LeRobot's `DiffusionModel`: `raw_diffusion`,
which the optimizer trains, and `diffusion`, its exponential moving average, which acts, gives the eval-mode
loss and is saved under LeRobot's usual keys (so metrics, hub checkpoints and LeRobot's own `diffusion`
policy loading a pacdp `model.safetensors` all get the EMA weights). `raw_diffusion.*` keys and the
`num_updates` counter are what resume needs on top.
"""

import contextlib
import copy
import functools
import logging
import math
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionPolicy
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
from lerobot_pacdp.certification import data_free_reference, freeze_deterministic
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.ema import ema_decay, update_ema
from lerobot_pacdp.module_swaps import child_replaced
from lerobot_pacdp.objective import pac_bayes_objective
from lerobot_pacdp.training_set import training_set_size
from lerobot_pacdp.uncertainty import (
    DEFAULT_SAMPLES,
    ChunkUncertainty,
    chunk_with_uncertainty,
    uncertainty_generator,
)

logger = logging.getLogger(__name__)

_BAYESIAN_KEY_SUFFIXES = ("_rho", "_prior_mu", "prior_rho")
_RAW_PREFIX = "raw_diffusion."
_UPDATES_KEY = "num_updates"
_FUSED_STEP_DEVICES = ("cpu", "cuda")  # devices where torch's Adam and AdamW have a fused step


class CheckpointMismatchError(RuntimeError):
    """A checkpoint's tensors do not match the PAC-DP network they are loaded into."""


class NonFiniteTrainingError(FloatingPointError):
    """Training produced a non-finite loss or weights; raised before any checkpoint could keep them."""


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
        if config.bayesian:
            keep_deterministic = (lambda name: False) if config.bayesian_conditioning else is_conditioning_projection
            bayesianize(self.diffusion.unet, config.prior_rho, keep_deterministic)
        if config.freeze_deterministic:  # before the EMA copy, so both copies hold the reference
            freeze_deterministic(self.diffusion, data_free_reference(config))
        self.raw_diffusion: DiffusionModel | None = None
        if config.use_ema:  # `diffusion` becomes the average; the optimizer trains a copy
            self.raw_diffusion = copy.deepcopy(self.diffusion)
            self.diffusion.requires_grad_(False)
        self.register_buffer(_UPDATES_KEY, torch.zeros((), dtype=torch.long))
        self._uncertainty_generator: torch.Generator | None = None
        if config.bayesian and config.num_train_samples is None and dataset_meta is not None:
            config.num_train_samples = training_set_size(dataset_meta, config.drop_n_last_frames).num_windows

    @property
    def trained_diffusion(self) -> DiffusionModel:
        """The network the optimizer updates: `raw_diffusion` with EMA, else `diffusion` itself."""
        return self.raw_diffusion if self.raw_diffusion is not None else self.diffusion

    @property
    def unet(self) -> torch.nn.Module:
        """The U-Net that acts (the EMA one when `use_ema`): what inference, metrics and certificates use."""
        return self.diffusion.unet

    def _acting(self, network: DiffusionModel) -> contextlib.AbstractContextManager:
        """Run LeRobot's DiffusionPolicy code with `network` in the place of `self.diffusion`."""
        return child_replaced(self, "diffusion", network)

    def get_optim_params(self) -> list[dict]:
        """The trained network's parameters; rho in its own group without weight decay (decay would pull
        sigma towards softplus(0)). The groups ask for torch's fused Adam/AdamW step (one kernel per tensor,
        not ~10) where the parameters' device has one; LeRobot's optimizer preset passes group options on."""
        trained = self.trained_diffusion
        fused = {"fused": True} if all(p.device.type in _FUSED_STEP_DEVICES for p in trained.parameters()) else {}
        if not self.config.bayesian:
            return [{"params": list(trained.parameters()), **fused}]
        rho = rho_parameters(trained.unet)
        rho_ids = {id(p) for p in rho}
        others = [p for p in trained.parameters() if id(p) not in rho_ids and p.requires_grad]
        return [{"params": others, **fused}, {"params": rho, "weight_decay": 0.0, **fused}]

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Training: Eq. 9 with one weight sample (the plain denoising loss when not Bayesian).
        Eval: the acting network's (EMA, posterior-mean) denoising error, i.e. the held-out NPE."""
        if not self.training:
            npe, _ = super().forward(batch)
            return npe, {"denoise_loss": npe.item()}
        trained = self.trained_diffusion
        if not self.config.bayesian:
            with self._acting(trained):
                risk, _ = super().forward(batch)
            parts = {"denoise_loss": risk.item()}
            self._check_finite(parts)
            return risk, parts

        num_samples = self.config.num_train_samples
        if num_samples is None:
            raise ValueError(
                "PAC-DP needs N (`num_train_samples`) to train, and no dataset was given to derive it. "
                "Pass --policy.num_train_samples=<number of training windows>."
            )
        with sampled_weights(trained.unet), self._acting(trained):  # one weight sample for this forward pass
            risk, _ = super().forward(batch)
            with torch.set_grad_enabled(self.config.kl_weight > 0):
                kl = kl_divergence(trained.unet)
            sigma_mean = mean_posterior_sigma(trained.unet)
        objective = pac_bayes_objective(risk, kl, num_samples, self.config.delta, self.config.kl_weight)
        terms = (risk, kl.to(risk.dtype), objective.sqrt_term, objective.linear_term)
        values = torch.stack([t.detach() for t in terms]).tolist()  # one host sync for the four logged parts
        parts = dict(zip(("denoise_loss", "kl", "bound_sqrt_term", "bound_linear_term"), values, strict=True))
        self._check_finite(parts)
        return objective.total, {**parts, "sigma_mean": sigma_mean}

    def _non_finite_tensors(self) -> list[str]:
        return [k for k, v in self.state_dict().items() if v.is_floating_point() and not v.isfinite().all()]

    def _check_finite(self, parts: dict[str, float]) -> None:
        """Stop at the first non-finite loss, saying which term and whether the weights were already lost."""
        bad = [name for name, value in parts.items() if not math.isfinite(value)]
        if not bad:
            return
        cause = (
            "the trained weights are already non-finite: the previous optimizer step had a non-finite gradient; "
            "lower the learning rate"
            if any(k.startswith(("raw_diffusion.", "diffusion.")) for k in self._non_finite_tensors())
            else "the weights are finite, so this batch holds NaN/inf values: check the dataset (the pacdp "
            "converters refuse them)"
        )
        raise NonFiniteTrainingError(
            f"PAC-DP: non-finite loss at training step {int(self.num_updates) + 1}: "
            + ", ".join(f"{name} = {value}" for name, value in parts.items())
            + f" (non-finite: {', '.join(bad)}); {cause}. Training stopped; no checkpoint holds a non-finite weight."
        )

    def update(self) -> None:
        """After each optimizer step (LeRobot's hook): the EMA step."""
        if self.raw_diffusion is not None:
            decay = ema_decay(int(self.num_updates), self.config.ema_power, self.config.ema_max_decay)
            update_ema(self.diffusion, self.raw_diffusion, decay)
        self.num_updates += 1

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """LeRobot's save, refused for non-finite weights (a non-finite gradient in the last step before a
        checkpoint; earlier ones are caught by the next step's loss)."""
        bad = self._non_finite_tensors()
        if bad:
            raise NonFiniteTrainingError(
                f"PAC-DP: refusing to save a checkpoint after update {int(self.num_updates)}: {len(bad)} tensors "
                f"are non-finite (e.g. {bad[:3]}), from a non-finite gradient; lower the learning rate."
            )
        super()._save_pretrained(save_directory, state_dict)

    def inference_weights(self, generator: torch.Generator | None = None) -> contextlib.AbstractContextManager:
        """The weights one action chunk is generated with (paper Algorithm 2)."""
        if self.config.inference_mode == "sample":
            return sampled_weights(self.unet, generator)
        return contextlib.nullcontext()

    def reset(self) -> None:
        super().reset()
        self.uncertainty_trace: list[ChunkUncertainty] = []  # one per chunk while `uncertainty_samples` > 0

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        if self.config.uncertainty_samples:  # same actions; their uncertainty is recorded beside them
            chunk = self.predict_with_uncertainty(batch, noise)
            self.uncertainty_trace.append(chunk)
            return chunk.actions
        return self._acting_chunk(batch, noise)

    def _acting_chunk(self, batch: dict[str, Tensor], noise: Tensor | None) -> Tensor:
        with self.inference_weights():
            return super().predict_action_chunk(batch, noise=noise)

    @torch.no_grad()
    def predict_with_uncertainty(
        self, batch: dict[str, Tensor], noise: Tensor | None = None, num_samples: int | None = None,
        generator: torch.Generator | None = None,
    ) -> ChunkUncertainty:
        """The chunk `predict_action_chunk` returns and how much K posterior weight samples (and K initial
        noises) disagree on it (`lerobot_pacdp.uncertainty`); K = `num_samples`, else `uncertainty_samples`,
        else 8. The draws come from `generator` (default: the policy's own), never the global RNG."""
        if generator is None:
            if self._uncertainty_generator is None:
                self._uncertainty_generator = uncertainty_generator(self.num_updates.device)
            generator = self._uncertainty_generator
        num_samples = num_samples or self.config.uncertainty_samples or DEFAULT_SAMPLES
        act = functools.partial(self._acting_chunk, batch, noise)
        return chunk_with_uncertainty(self.diffusion, act, num_samples, generator)

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Load strictly: LeRobot only warns on missing keys, which would silently drop a posterior.

        A checkpoint saved before EMA existed (no `raw_diffusion.*`, no `num_updates`) loads as a run whose
        average restarts from its weights."""
        missing, unexpected = load_model_as_safetensor(
            model, model_file, strict=False, device=resolve_safetensors_device(map_location)
        )
        pre_ema = [k for k in missing if k.startswith(_RAW_PREFIX) or k == _UPDATES_KEY]
        if pre_ema and len(pre_ema) == len(missing) and not unexpected:
            if model.raw_diffusion is not None:
                model.raw_diffusion.load_state_dict(model.diffusion.state_dict())
            logger.warning("%s predates pacdp's EMA: the average starts from its weights.", Path(model_file))
            missing = []
        if missing or unexpected:
            bayesian = [k for k in (*missing, *unexpected) if k.endswith(_BAYESIAN_KEY_SUFFIXES)]
            raise CheckpointMismatchError(
                f"{Path(model_file)} does not match this PAC-DP network: "
                f"{len(missing)} missing keys {sorted(missing)[:6]}, {len(unexpected)} unexpected keys "
                f"{sorted(unexpected)[:6]} ({len(bayesian)} of them Bayesian mu/rho/prior tensors). "
                "Was it saved by a different policy type, or with a different `bayesian`, `use_ema`, "
                "`bayesian_conditioning` or U-Net size? Load it with the config.json saved beside it."
            )
        return model
