"""Load a PAC-DP checkpoint from Python and query action chunks in both inference modes.

    python examples/query_actions.py --checkpoint outputs/train/pusht_pacdp/checkpoints/last/pretrained_model

`--checkpoint` is a local `pretrained_model` directory or a hub repo id (`<user>/<repo>`).
"""

import argparse

import torch
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.modeling_pacdp import PacdpPolicy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True)
    args = parser.parse_args()

    policy = PacdpPolicy.from_pretrained(args.checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=args.checkpoint)
    config = policy.config
    print(f"Loaded pacdp: N={config.num_train_samples}, lambda={config.kl_weight}, prior rho={config.prior_rho}")

    # One observation in the raw (unnormalised) units of the dataset, e.g. PushT pixels.
    observation = {
        key: torch.full(feature.shape, 256.0) for key, feature in config.input_features.items()
    }
    action_dim = config.output_features["action"].shape[0]
    noise = torch.randn(1, config.horizon, action_dim)  # same initial noise, so differences come from the weights
    for mode in ("mean", "sample"):
        config.inference_mode = mode  # an inference-time switch: no reload needed
        chunks = []
        for _ in range(2):
            policy.reset()  # new episode: empty the observation/action queues
            batch = preprocessor(dict(observation))
            batch = {k: v.unsqueeze(1).repeat(1, config.n_obs_steps, 1) for k, v in batch.items() if k in observation}
            chunks.append(postprocessor(policy.predict_action_chunk(batch, noise=noise)))
        same = torch.allclose(chunks[0], chunks[1])
        print(f"{mode:>6} mode: chunk shape {tuple(chunks[0].shape)}, first action {chunks[0][0, 0].tolist()}, "
              f"two calls {'identical' if same else 'differ (one posterior sample per chunk)'}")


if __name__ == "__main__":
    main()
