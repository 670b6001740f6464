"""Publish a trained PAC-DP checkpoint to the Hugging Face hub with LeRobot's own push code.

    python examples/publish_to_hub.py --checkpoint outputs/pusht_pacdp/train/checkpoints/last/pretrained_model \
        --repo-id <user>/<repo>

This is what `lerobot-train ... --policy.repo_id=<user>/<repo> --policy.push_to_hub=true` does at the
end of training, for a checkpoint you already have: weights (mu, rho and the prior), config.json,
train_config.json, the processors and a generated model card. Needs `hf auth login` (or HF_TOKEN).
Anyone can then run `lerobot-eval --policy.path=<user>/<repo> ...`.
"""

import argparse

from lerobot.configs.train import TrainPipelineConfig
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.modeling_pacdp import PacdpPolicy


def publish(checkpoint: str, repo_id: str, private: bool = False) -> None:
    policy = PacdpPolicy.from_pretrained(checkpoint)
    policy.config.repo_id, policy.config.private = repo_id, private
    train_config = TrainPipelineConfig.from_pretrained(checkpoint)
    policy.push_model_to_hub(train_config)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=checkpoint)
    preprocessor.push_to_hub(repo_id)
    postprocessor.push_to_hub(repo_id)
    print(f"published {checkpoint} to {repo_id}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="a lerobot-train .../pretrained_model directory")
    parser.add_argument("--repo-id", required=True, help="<user>/<repo> on the hub")
    parser.add_argument("--private", action="store_true")
    args = parser.parse_args(argv)
    publish(args.checkpoint, args.repo_id, args.private)


if __name__ == "__main__":
    main()
