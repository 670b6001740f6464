"""Sharing on the hub: the real LeRobot push/load code against local directories in the hub layout."""

import json

import pytest
import torch
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.modeling_pacdp import PacdpPolicy

from pacdp_testing import LocalHub, install_into_hf_cache, make_tiny_dataset, tiny_config

REPO_ID = "someone/pacdp_tiny"


@pytest.fixture
def local_hub(tmp_path, monkeypatch):
    import lerobot.policies.pretrained
    import lerobot.utils.hub

    LocalHub.root = tmp_path / "hub"
    monkeypatch.setattr(lerobot.policies.pretrained, "HfApi", LocalHub)
    monkeypatch.setattr(lerobot.utils.hub, "HfApi", LocalHub)
    # ModelCard.validate() asks the hub's web API to lint the card: the one network call left.
    monkeypatch.setattr("huggingface_hub.ModelCard.validate", lambda self, repo_type=None: None)
    return LocalHub.root


def test_push_writes_weights_configs_processors_and_a_model_card_then_loads_back_by_repo_id(
    tmp_path, local_hub, monkeypatch
):
    dataset = make_tiny_dataset(tmp_path / "data", [20, 20])
    torch.manual_seed(0)
    config = tiny_config(repo_id=REPO_ID, push_to_hub=True)
    policy = PacdpPolicy(config)
    train_cfg = TrainPipelineConfig(dataset=DatasetConfig(repo_id="local/tiny"), policy=config, steps=3)
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=dataset.meta.stats)

    policy.push_model_to_hub(train_cfg, dataset_meta=dataset.meta)
    preprocessor.push_to_hub(REPO_ID)
    postprocessor.push_to_hub(REPO_ID)

    repo = local_hub / REPO_ID
    files = {p.name for p in repo.iterdir()}
    assert {"config.json", "model.safetensors", "train_config.json", "README.md"} <= files
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= files
    assert json.loads((repo / "config.json").read_text())["type"] == "pacdp"
    card = (repo / "README.md").read_text()
    assert "pacdp" in card and "library_name: lerobot" in card and "local/tiny" in card

    # Load it back through huggingface_hub's offline cache, exactly as `--policy.path=<user>/<repo>` does.
    cache = tmp_path / "hf_cache"
    install_into_hf_cache(repo, REPO_ID, cache)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_OFFLINE", True)
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(cache))
    loaded = PacdpPolicy.from_pretrained(REPO_ID, cache_dir=cache)
    for key, value in policy.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    pre, _ = make_pre_post_processors(loaded.config, pretrained_path=REPO_ID)
    assert len(pre.steps) == len(preprocessor.steps)


@pytest.mark.slow
def test_publish_example_uploads_a_lerobot_train_checkpoint(tmp_path, local_hub):
    """examples/publish_to_hub.py on a real lerobot-train checkpoint (trained here in-process)."""
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    data = tmp_path / "data"
    make_tiny_dataset(data, [30, 30])
    out = tmp_path / "train"
    subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-train"), "--policy.type=pacdp", "--policy.down_dims=[16,32]",
         "--policy.horizon=8", "--policy.n_action_steps=4", "--policy.drop_n_last_frames=3",
         "--policy.diffusion_step_embed_dim=16", "--policy.device=cpu", "--policy.push_to_hub=false",
         "--dataset.repo_id=local/tiny", f"--dataset.root={data}", "--steps=2", "--batch_size=4",
         "--wandb.enable=false", "--num_workers=0", f"--output_dir={out}"],
        check=True, capture_output=True, env={**__import__("os").environ, "HF_HUB_OFFLINE": "1"}, timeout=600,
    )
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    spec = importlib.util.spec_from_file_location("publish_to_hub", Path(__file__).parents[1] / "examples" / "publish_to_hub.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--checkpoint", str(checkpoint), "--repo-id", REPO_ID])
    repo = local_hub / REPO_ID
    assert {p.name for p in checkpoint.iterdir()} <= {p.name for p in repo.iterdir()}
    assert (repo / "README.md").read_text().count("pacdp") >= 1
    assert (repo / "model.safetensors").read_bytes() == (checkpoint / "model.safetensors").read_bytes()
