"""Test helpers: tiny PAC-DP configs and batches (fast on 2 CPU cores), and where the shared demo data lives."""

from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"
PUSHT_ZARR = SHARED_DIR / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"

STATE_DIM, ENV_DIM, ACTION_DIM = 2, 16, 2


def tiny_features() -> tuple[dict, dict]:
    inputs = {
        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (ENV_DIM,)),
    }
    outputs = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    return inputs, outputs


def tiny_config(**overrides) -> PacdpConfig:
    """A PushT-shaped PAC-DP config with a very small U-Net."""
    values = dict(
        down_dims=(16, 32),
        diffusion_step_embed_dim=16,
        horizon=8,
        n_action_steps=4,
        drop_n_last_frames=3,
        num_train_samples=1000,
        device="cpu",
    )
    values.update(overrides)
    config = PacdpConfig(**values)
    config.input_features, config.output_features = tiny_features()
    return config


def random_batch(config: PacdpConfig, batch_size: int = 4, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    n_obs, horizon = config.n_obs_steps, config.horizon
    is_pad = torch.zeros(batch_size, horizon, dtype=torch.bool)
    is_pad[0, -2:] = True
    return {
        "observation.state": torch.randn(batch_size, n_obs, STATE_DIM, generator=generator),
        "observation.environment_state": torch.randn(batch_size, n_obs, ENV_DIM, generator=generator),
        "action": torch.randn(batch_size, horizon, ACTION_DIM, generator=generator),
        "action_is_pad": is_pad,
    }


def train_steps(policy: PacdpPolicy, steps: int, lr: float = 1e-2) -> list[dict[str, torch.Tensor]]:
    """lerobot-train's step on random batches: Eq. 9 forward, backward, an Adam step, then `update()` (the EMA).
    Returns the trained weights after each step, before its EMA update."""
    policy.train()
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=lr)
    history = []
    for step in range(steps):
        loss, _ = policy.forward(random_batch(policy.config, seed=step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append({k: v.detach().clone() for k, v in policy.trained_diffusion.named_parameters()})
        policy.update()
    return history


def make_tiny_dataset(root: Path, episode_lengths: list[int], seed: int = 0, repo_id: str = "local/tiny"):
    """A small PushT-shaped LeRobotDataset (state 2, env 16, action 2) at `root`, fps 10."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": ["x", "y"]},
        "observation.environment_state": {"dtype": "float32", "shape": (ENV_DIM,), "names": None},
        "action": {"dtype": "float32", "shape": (ACTION_DIM,), "names": ["x", "y"]},
    }
    dataset = LeRobotDataset.create(repo_id, fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(seed)
    for length in episode_lengths:
        for _ in range(length):
            dataset.add_frame(
                {
                    "observation.state": rng.normal(size=STATE_DIM).astype(np.float32),
                    "observation.environment_state": rng.normal(size=ENV_DIM).astype(np.float32),
                    "action": rng.normal(size=ACTION_DIM).astype(np.float32),
                    "task": "tiny task",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return LeRobotDataset(repo_id, root=root)


class LocalHub:
    """Stands in for `huggingface_hub.HfApi`: uploads land in `root/<repo_id>/` instead of the network.

    Only the two calls LeRobot's push code makes are implemented, with the same arguments, so the
    real `push_model_to_hub` / `push_to_hub` code paths run unchanged.
    """

    root: Path

    def __init__(self, token=None, **_):
        self.token = token

    def create_repo(self, repo_id: str, private=None, exist_ok=False, **_):
        from types import SimpleNamespace

        (self.root / repo_id).mkdir(parents=True, exist_ok=True)
        return SimpleNamespace(repo_id=repo_id)

    def upload_folder(self, repo_id, folder_path, allow_patterns=None, ignore_patterns=None, **_):
        import fnmatch
        import shutil
        from types import SimpleNamespace

        for path in Path(folder_path).rglob("*"):
            name = path.name
            if path.is_dir() or (allow_patterns and not any(fnmatch.fnmatch(name, p) for p in allow_patterns)):
                continue
            if ignore_patterns and any(fnmatch.fnmatch(name, p) for p in ignore_patterns):
                continue
            target = self.root / repo_id / path.relative_to(folder_path)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
        return SimpleNamespace(repo_url=SimpleNamespace(url=f"file://{self.root / repo_id}"))


def install_into_hf_cache(repo_dir: Path, repo_id: str, cache_dir: Path, commit: str = "0" * 40) -> None:
    """Lay a model repo's files out as huggingface_hub's cache does, so offline hub loading finds them."""
    import shutil

    base = cache_dir / f"models--{repo_id.replace('/', '--')}"
    shutil.copytree(repo_dir, base / "snapshots" / commit)
    (base / "refs").mkdir(parents=True)
    (base / "refs" / "main").write_text(commit)
