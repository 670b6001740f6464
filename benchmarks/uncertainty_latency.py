"""Latency of the posterior uncertainty (K weight samples) against one action chunk, and batched vs sequential.

    OMP_NUM_THREADS=1 python benchmarks/uncertainty_latency.py --threads 1 --batch-sizes 1 5 --rounds 7

Times, per round and interleaved so load changes hit every variant alike, on the Lift CPU preset's U-Net
(configs/robomimic/lift_cpu.json, Lift's state, object and action sizes, DDIM 10 steps; the weights' values
do not matter; the policy of results/uncertainty):
one chunk (`predict_action_chunk`, mean mode); the K posterior chunks as one vmapped pass over K stacked
weight sets (weight draw included) and as K sequential passes (`sampled_weights`, one per pass); the K noise
chunks (K x B rows of one sampler call); and all of `predict_with_uncertainty`. Medians of wall and CPU
seconds go to results/uncertainty/latency.json with the machine's load.
"""

import argparse
import json
import os
import time
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.bayesian_layers import sampled_weights
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy
from lerobot_pacdp.robomimic.tasks import get_task
from lerobot_pacdp.uncertainty import noise_chunks, posterior_chunks

PRESET = Path(__file__).resolve().parents[1] / "configs" / "robomimic" / "lift_cpu.json"
LIFT = get_task("lift")
STATE, ENV, ACTION = LIFT.state_dim, LIFT.object_dim, LIFT.action_dim


def lift_cpu_policy() -> PacdpPolicy:
    preset = json.loads(PRESET.read_text())["policy"]
    config = PacdpConfig(down_dims=tuple(preset["down_dims"]), diffusion_step_embed_dim=preset["diffusion_step_embed_dim"],
                         num_train_samples=1000, device="cpu")  # fmt: skip
    config.input_features = {
        "observation.state": PolicyFeature(FeatureType.STATE, (STATE,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (ENV,)),
    }
    config.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION,))}
    torch.manual_seed(0)
    return PacdpPolicy(config).eval()


def variants(policy: PacdpPolicy, batch_size: int, k: int) -> dict:
    model, config = policy.diffusion, policy.config
    window = {
        "observation.state": torch.randn(batch_size, config.n_obs_steps, STATE),
        "observation.environment_state": torch.randn(batch_size, config.n_obs_steps, ENV),
    }
    noise = torch.randn(batch_size, config.horizon, ACTION)
    cond = model._prepare_global_conditioning(window)
    generator = torch.Generator().manual_seed(0)

    def posterior_sequential():
        chunks = []
        for _ in range(k):
            with sampled_weights(model.unet, generator):
                chunks.append(model.conditional_sample(batch_size, cond, generator, noise))
        return torch.stack(chunks)

    return {
        "one_chunk": lambda: policy.predict_action_chunk(window, noise),
        "posterior_k_batched": lambda: posterior_chunks(model, cond, noise, k, generator),
        "posterior_k_sequential": posterior_sequential,
        "noise_k_batched": lambda: noise_chunks(model, cond, noise, k, generator),
        "predict_with_uncertainty": lambda: policy.predict_with_uncertainty(window, noise, num_samples=k, generator=generator),
    }


def measure(batch_sizes: list[int], k: int, rounds: int) -> dict:
    policy = lift_cpu_policy()
    results = {}
    with torch.no_grad():
        for batch_size in batch_sizes:
            calls = variants(policy, batch_size, k)
            for call in calls.values():  # warm-up
                call()
            samples = {name: {"wall_s": [], "cpu_s": []} for name in calls}
            for _ in range(rounds):
                for name, call in calls.items():
                    wall, cpu = time.perf_counter(), time.process_time()
                    call()
                    samples[name]["wall_s"].append(time.perf_counter() - wall)
                    samples[name]["cpu_s"].append(time.process_time() - cpu)
            medians = {name: {kind: float(torch.tensor(v).median()) for kind, v in s.items()} for name, s in samples.items()}
            one = medians["one_chunk"]["cpu_s"]
            results[f"batch_{batch_size}"] = {
                "median": medians,
                "cpu_time_over_one_chunk": {name: m["cpu_s"] / one for name, m in medians.items()},
            }
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 5])
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--output", type=Path, default=Path("results/uncertainty/latency.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    results = measure(args.batch_sizes, args.samples, args.rounds)
    payload = {
        "command": f"OMP_NUM_THREADS={args.threads} python benchmarks/uncertainty_latency.py --threads {args.threads} "
        f"--batch-sizes {' '.join(map(str, args.batch_sizes))} --samples {args.samples} --rounds {args.rounds}",
        "device": "cpu", "threads": args.threads, "samples": args.samples, "rounds": args.rounds,
        "load_average_1min": [load_before, os.getloadavg()[0]], "cpu_count": os.cpu_count(),
        "results": results,
    }  # fmt: skip
    write_text_atomic(args.output, json.dumps(payload, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
