"""Configuration of PAC-DP, registered with LeRobot as policy type `pacdp`.

PAC-DP keeps LeRobot's diffusion policy (observation encoders, U-Net, schedulers, processors) and
changes two things: the noise-prediction U-Net becomes a Bayesian network, and training minimises
the PAC-Bayes objective of paper Eq. 9. So the config is `DiffusionConfig` plus the PAC-Bayes
hyper-parameters, with defaults switched to Diffusion Policy's state-based setup.
"""

import copy
import math
from dataclasses import dataclass, field, fields

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

INFERENCE_MODES = ("mean", "sample")


@PreTrainedConfig.register_subclass("pacdp")
@dataclass
class PacdpConfig(DiffusionConfig):
    """PAC-DP policy configuration.

    Args:
        bayesian: True makes the U-Net Bayesian and trains on Eq. 9 (PAC-DP, or BDP with kl_weight=0);
            False builds the same policy with deterministic layers trained on the plain denoising loss:
            the DP baseline that differs from PAC-DP only in what the paper changes.
        kl_weight: lambda in paper Eq. 9. 0 gives the BDP baseline (Bayesian U-Net, no KL pressure).
            The paper's values: PushT 1e-4; Lift/Can/ToolHang 1e-5; Square/Transport 1e-6.
        prior_rho: rho of the prior P; prior sigma = softplus(prior_rho) (Eq. 7). -4.5 gives 0.0110.
        delta: confidence parameter of the bound (Eq. 9), in (0, 1).
        num_train_samples: N in Eq. 9. None lets lerobot-train derive it from the dataset it trains on
            (the windows its sampler draws: frames of the training episodes minus `drop_n_last_frames`
            each, held-out split excluded) and write it back here, so it is saved in config.json.
        bayesian_conditioning: False keeps the FiLM conditioning projections deterministic (the
            paper's architecture); True makes them Bayesian too (the paper's "Full BN" ablation).
        inference_mode: "mean" acts with the posterior mean mu; "sample" draws one weight sample per
            generated action chunk (paper Algorithm 2).
        use_ema: act, evaluate and publish with an exponential moving average of the trained weights, as
            Diffusion Policy does (`lerobot_pacdp.ema`: Chi et al.'s schedule).
        ema_power, ema_max_decay: the EMA warm-up exponent and the cap of its decay (Chi: 0.75, 0.9999).
        freeze_deterministic: keep every non-Bayesian tensor (FiLM projections, GroupNorm, observation
            encoders) at a value fixed before training (`lerobot_pacdp.certification`), so that only the
            posterior depends on the demonstrations, as `pacdp-certify` requires.
        uncertainty_samples: K > 0 records, for every generated chunk, how much K posterior weight samples
            (and K initial noises) disagree on it (`lerobot_pacdp.uncertainty`); the actions are unchanged.
            Under lerobot-eval each episode's values are written beside eval_info.json. 0: off.
    """

    # PAC-Bayes objective and posterior.
    bayesian: bool = True
    kl_weight: float = 1e-4
    prior_rho: float = -4.5
    delta: float = 0.025
    num_train_samples: int | None = None
    bayesian_conditioning: bool = False
    inference_mode: str = "mean"
    use_ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    freeze_deterministic: bool = False
    uncertainty_samples: int = 0

    # Diffusion Policy's state-based setup (Chi et al.), not LeRobot's image-based defaults.
    horizon: int = 16
    n_obs_steps: int = 2
    n_action_steps: int = 8
    drop_n_last_frames: int = 7  # horizon - n_action_steps - n_obs_steps + 1
    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel_size: int = 5
    diffusion_step_embed_dim: int = 256
    num_train_timesteps: int = 100
    beta_schedule: str = "squaredcos_cap_v2"
    prediction_type: str = "epsilon"
    # The paper samples with DDIM in 10 steps.
    noise_scheduler_type: str = "DDIM"
    num_inference_steps: int | None = 10
    # R in Eq. 9 is the denoising error on real actions only, not on copy-padded ones.
    do_mask_loss_for_padding: bool = True
    # State-based Diffusion Policy normalises every observation; LeRobot leaves ENV raw by default.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        if not (math.isfinite(self.kl_weight) and self.kl_weight >= 0):
            raise ValueError(
                f"`kl_weight` (lambda) must be a finite number >= 0, got {self.kl_weight}. "
                "Use 0 for the BDP baseline, or the paper's 1e-4 (PushT) / 1e-5 / 1e-6 (robomimic)."
            )
        if not math.isfinite(self.prior_rho):
            raise ValueError(
                f"`prior_rho` must be a finite number, got {self.prior_rho}. "
                "The paper uses -4.5 (prior sigma = softplus(-4.5) = 0.011)."
            )
        if not (0.0 < self.delta < 1.0):
            raise ValueError(f"`delta` must lie strictly between 0 and 1, got {self.delta} (paper: 0.025).")
        if self.num_train_samples is not None and self.num_train_samples < 1:
            raise ValueError(
                f"`num_train_samples` (N) must be >= 1, got {self.num_train_samples}. "
                "Leave it unset to derive N from the training dataset."
            )
        if self.inference_mode not in INFERENCE_MODES:
            raise ValueError(
                f"`inference_mode` must be one of {INFERENCE_MODES}, got {self.inference_mode!r}."
            )
        if not self.bayesian and self.inference_mode == "sample":
            raise ValueError(
                "`inference_mode='sample'` needs a Bayesian U-Net, but `bayesian=False`. "
                "Use `inference_mode=mean`, or `bayesian=true`."
            )
        if self.freeze_deterministic and not self.bayesian:
            raise ValueError(
                "`freeze_deterministic=True` freezes everything but the posterior, and `bayesian=False` has "
                "none: nothing would train. Use `bayesian=true` or `freeze_deterministic=false`."
            )
        if not (math.isfinite(self.ema_power) and self.ema_power > 0):
            raise ValueError(f"`ema_power` must be a finite number > 0, got {self.ema_power} (Chi et al.: 0.75).")
        if not (0.0 <= self.ema_max_decay < 1.0):
            raise ValueError(
                f"`ema_max_decay` must lie in [0, 1), got {self.ema_max_decay} (Chi et al.: 0.9999). "
                "Use `use_ema=false` to act with the trained weights themselves."
            )
        if self.uncertainty_samples < 0 or self.uncertainty_samples == 1:
            raise ValueError(
                f"`uncertainty_samples` must be 0 (off) or at least 2 (a spread needs two samples), got "
                f"{self.uncertainty_samples}. The measured setting is 8."
            )
        if self.compile_model:
            raise ValueError(
                "`compile_model=True` is not supported by pacdp: LeRobot compiles the U-Net before its "
                "layers are made Bayesian. Leave `--policy.compile_model=false`."
            )

    def diffusion_twin(self) -> DiffusionConfig:
        """LeRobot's `diffusion` config with every shared field equal to this one (no EMA, no Bayesian layers)."""
        shared = {f.name: getattr(self, f.name) for f in fields(DiffusionConfig) if f.init}
        return DiffusionConfig(**copy.deepcopy(shared))

    @classmethod
    def from_diffusion(cls, config: DiffusionConfig, **changes) -> "PacdpConfig":
        """The inverse of `diffusion_twin`: every field `config` (a `diffusion` or `pacdp` config) shares with
        PacdpConfig, the PAC-Bayes fields of a `pacdp` one included, then `changes`."""
        own = {f.name for f in fields(cls) if f.init}
        shared = {f.name: getattr(config, f.name) for f in fields(config) if f.init and f.name in own}
        return cls(**(copy.deepcopy(shared) | changes))
