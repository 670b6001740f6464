"""Configuration of PAC-DP, registered with LeRobot as policy type `pacdp`.

PAC-DP keeps LeRobot's diffusion policy (observation encoders, U-Net, schedulers, processors) and
changes two things: the noise-prediction U-Net becomes a Bayesian network, and training minimises
the PAC-Bayes objective of paper Eq. 9. So the config is `DiffusionConfig` plus the PAC-Bayes
hyper-parameters, with defaults switched to Diffusion Policy's state-based setup.
"""

import math
from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

INFERENCE_MODES = ("mean", "sample")


@PreTrainedConfig.register_subclass("pacdp")
@dataclass
class PacdpConfig(DiffusionConfig):
    """PAC-DP policy configuration.

    Args:
        kl_weight: lambda in paper Eq. 9. 0 gives the BDP baseline (Bayesian U-Net, no KL pressure).
            The paper's values (PushT 1e-4; Lift/Can/ToolHang 1e-5; Square/Transport 1e-6) are on the
            scale where N counts training frames, as `num_train_samples` does here.
        prior_rho: rho of the prior P; prior sigma = softplus(prior_rho) (Eq. 7). -4.5 gives 0.0110.
        delta: confidence parameter of the bound (Eq. 9), in (0, 1).
        num_train_samples: N in Eq. 9. None derives it at construction from the dataset actually
            used for training (frames of the selected training episodes, held-out split excluded) and
            writes it back here, so it is saved in config.json and reused on resume.
        bayesian_conditioning: False keeps the FiLM conditioning projections deterministic (the
            paper's architecture); True makes them Bayesian too (the paper's "Full BN" ablation).
        inference_mode: "mean" acts with the posterior mean mu; "sample" draws one weight sample per
            generated action chunk (paper Algorithm 2).
    """

    # PAC-Bayes objective and posterior.
    kl_weight: float = 1e-4
    prior_rho: float = -4.5
    delta: float = 0.025
    num_train_samples: int | None = None
    bayesian_conditioning: bool = False
    inference_mode: str = "mean"

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
        if self.compile_model:
            raise ValueError(
                "`compile_model=True` is not supported by pacdp: LeRobot compiles the U-Net before its "
                "layers are made Bayesian. Leave `--policy.compile_model=false`."
            )
