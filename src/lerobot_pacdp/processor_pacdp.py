"""Pre/post-processors for PAC-DP: exactly LeRobot's diffusion pipelines.

The Bayesian U-Net sees the same normalised inputs as Diffusion Policy; the only difference lives in
the config (`ENV` features are normalised too, see `PacdpConfig.normalization_mapping`).
"""

from typing import Any

import torch
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors
from lerobot.processor import PolicyAction, PolicyProcessorPipeline

from lerobot_pacdp.configuration_pacdp import PacdpConfig


def make_pacdp_pre_post_processors(
    config: PacdpConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    return make_diffusion_pre_post_processors(config, dataset_stats)
