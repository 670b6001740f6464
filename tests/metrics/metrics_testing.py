"""Helpers of the metrics tests: tiny configs and lerobot-train-shaped run directories (no lerobot-train run)."""

from pathlib import Path

import torch
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.certification import deterministic_tensors
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import tiny_config, tiny_features

REPO_ID = "local/tiny"
EPISODE_LENGTHS = [14, 18, 16, 20, 15, 17]  # eval_split 0.34 holds out the last 3
EVAL_SPLIT = 0.34
STEPS = (100, 200, 300)
TINY_NET = dict(down_dims=(8, 16), diffusion_step_embed_dim=8, horizon=8, n_action_steps=4, drop_n_last_frames=3)


def pacdp_config(**overrides):
    return tiny_config(**{**TINY_NET, **overrides})


def diffusion_config() -> DiffusionConfig:
    """LeRobot's own `diffusion` policy (its normalisation mapping: ENV left raw), sampling with 10 DDIM steps."""
    config = DiffusionConfig(**TINY_NET, noise_scheduler_type="DDIM", num_inference_steps=10, device="cpu")
    config.input_features, config.output_features = tiny_features()
    return config


def save_checkpoint(
    policy, dataset: LeRobotDataset, pretrained_dir: Path, eval_split: float = EVAL_SPLIT, episodes=None
) -> Path:
    """What lerobot-train writes into checkpoints/<step>/pretrained_model: weights, config, processors
    (trained on `episodes`, default all, minus the eval split)."""
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=dataset.meta.stats)
    policy.save_pretrained(pretrained_dir)
    preprocessor.save_pretrained(pretrained_dir)
    postprocessor.save_pretrained(pretrained_dir)
    train_config = TrainPipelineConfig(
        dataset=DatasetConfig(repo_id=REPO_ID, root=str(dataset.root), eval_split=eval_split, episodes=episodes),
        policy=policy.config,
        output_dir=pretrained_dir.parents[2],
    )
    train_config._save_pretrained(pretrained_dir)
    return pretrained_dir


def perturb(policy, seed: int, scale: float = 0.05) -> None:
    """Stand-in for training: move every trained parameter a little (deterministically); with
    `freeze_deterministic` the deterministic tensors keep their reference, as in training."""
    frozen = set(deterministic_tensors(policy.diffusion)) if getattr(policy.config, "freeze_deterministic", False) else set()
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in policy.named_parameters():
            if name.split(".", 1)[1] not in frozen:
                parameter.add_(scale * torch.randn(parameter.shape, generator=generator))


def make_run(run_dir: Path, dataset: LeRobotDataset, kind: str, seed: int) -> Path:
    """A run directory with checkpoints/<step>/pretrained_model for STEPS and a `last` symlink."""
    for step in STEPS:
        torch.manual_seed(seed)
        if kind == "diffusion":
            policy = DiffusionPolicy(diffusion_config())
        else:
            frozen = kind == "pacdp_frozen"
            policy = PacdpPolicy(pacdp_config(kl_weight=0.0 if kind == "bdp" else 1e-4, freeze_deterministic=frozen))
        perturb(policy, seed * 1000 + step)
        save_checkpoint(policy, dataset, run_dir / "checkpoints" / f"{step:06d}" / "pretrained_model")
    (run_dir / "checkpoints" / "last").symlink_to(f"{STEPS[-1]:06d}")
    return run_dir
