"""DP vs PAC-DP cost on the same U-Net, batch and data: training step, action latency, peak memory.

Timings alternate between the two policies in one process (so background load hits both alike) and
report medians; peak memory is measured per policy in a fresh subprocess (CPU: peak RSS growth;
CUDA: torch.cuda.max_memory_allocated). Prints a table and writes JSON to benchmarks/results/.

    python benchmarks/speed.py --preset cpu          # 2 CPU cores, small U-Net
    python benchmarks/speed.py --preset paper        # paper U-Net (256/512/1024), batch 256, GPU
    python benchmarks/speed.py --preset paper --batch-size 8 --train-steps 10 --latency-calls 5  # on 2 CPU cores
"""

import argparse
import dataclasses
import json
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

RESULTS_DIR = Path(__file__).parent / "results"
STATE_DIM, ENV_DIM, ACTION_DIM = 2, 16, 2  # PushT, state-based


@dataclasses.dataclass(frozen=True)
class Preset:
    down_dims: tuple[int, ...]
    step_embed_dim: int
    batch_size: int
    train_steps: int
    latency_calls: int


PRESETS = {
    "cpu": Preset(down_dims=(64, 128, 256), step_embed_dim=64, batch_size=64, train_steps=20, latency_calls=10),
    "paper": Preset(down_dims=(256, 512, 1024), step_embed_dim=256, batch_size=256, train_steps=50, latency_calls=50),
}


def _features():
    inputs = {
        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (ENV_DIM,)),
    }
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}


def build(method: str, preset: Preset, device: str) -> torch.nn.Module:
    """DP gets PAC-DP's exact diffusion settings; only the Bayesian layers and the loss differ."""
    pacdp = PacdpConfig(
        down_dims=preset.down_dims,
        diffusion_step_embed_dim=preset.step_embed_dim,
        num_train_samples=25_650,
        device=device,
        inference_mode="sample" if method == "pacdp-sample" else "mean",
    )
    if method.startswith("pacdp"):
        config, policy_cls = pacdp, PacdpPolicy
    else:
        shared = {k: getattr(pacdp, k) for k in DiffusionConfig.__dataclass_fields__ if k in pacdp.__dataclass_fields__}
        config, policy_cls = DiffusionConfig(**shared), DiffusionPolicy
    config.input_features, config.output_features = _features()
    torch.manual_seed(0)
    return policy_cls(config).to(device)


def make_batch(preset: Preset, config, device: str) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    b, n_obs, h = preset.batch_size, config.n_obs_steps, config.horizon
    batch = {
        "observation.state": torch.randn(b, n_obs, STATE_DIM, generator=g),
        "observation.environment_state": torch.randn(b, n_obs, ENV_DIM, generator=g),
        "action": torch.randn(b, h, ACTION_DIM, generator=g),
        "action_is_pad": torch.zeros(b, h, dtype=torch.bool),
    }
    return {k: v.to(device) for k, v in batch.items()}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


class Trainer:
    def __init__(self, policy, batch, device):
        self.policy, self.batch, self.device = policy, batch, device
        self.optimizer = torch.optim.Adam(policy.get_optim_params(), lr=1e-4)
        policy.train()

    def step(self) -> float:
        _sync(self.device)
        start = time.perf_counter()
        loss, _ = self.policy.forward(self.batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        _sync(self.device)
        return time.perf_counter() - start


def chunk_latency(policy, batch, device) -> float:
    obs = {k: v[:1] for k, v in batch.items() if k.startswith("observation")}
    policy.eval()
    _sync(device)
    start = time.perf_counter()
    policy.predict_action_chunk(obs)
    _sync(device)
    return time.perf_counter() - start


def measure_times(preset: Preset, device: str) -> dict[str, float]:
    """Median seconds per training step and per action chunk, interleaving the methods."""
    methods = ("dp", "pacdp", "pacdp-sample")
    policies = {m: build(m, preset, device) for m in methods}
    batch = make_batch(preset, policies["dp"].config, device)
    trainers = {m: Trainer(policies[m], batch, device) for m in ("dp", "pacdp")}
    step_times: dict[str, list[float]] = {m: [] for m in trainers}
    for i in range(preset.train_steps + 3):
        for m, trainer in trainers.items():
            t = trainer.step()
            if i >= 3:  # warm-up
                step_times[m].append(t)
    latencies: dict[str, list[float]] = {m: [] for m in methods}
    with torch.no_grad():
        for i in range(preset.latency_calls + 3):
            for m in methods:
                t = chunk_latency(policies[m], batch, device)
                if i >= 3:
                    latencies[m].append(t)
    return {
        "dp_step_s": statistics.median(step_times["dp"]),
        "pacdp_step_s": statistics.median(step_times["pacdp"]),
        "dp_chunk_s": statistics.median(latencies["dp"]),
        "pacdp_mean_chunk_s": statistics.median(latencies["pacdp"]),
        "pacdp_sample_chunk_s": statistics.median(latencies["pacdp-sample"]),
    }


class _RssPeak(threading.Thread):
    """Samples this process's resident memory every millisecond and keeps the maximum."""

    def __init__(self):
        super().__init__(daemon=True)
        self.process, self.peak, self.running = psutil.Process(), 0, True

    def run(self):
        while self.running:
            self.peak = max(self.peak, self.process.memory_info().rss)
            time.sleep(1e-3)


def peak_memory_child(method: str, preset_name: str, device: str) -> None:
    """Run in a subprocess: a few training steps, then print the peak memory they needed (bytes).

    CPU: peak resident memory during model construction and training minus the resident memory
    before it (weights, gradients, optimizer state, activations). CUDA: peak allocated memory.
    """
    preset = PRESETS[preset_name]
    baseline = psutil.Process().memory_info().rss
    sampler = _RssPeak()
    sampler.start()
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    policy = build(method, preset, device)
    trainer = Trainer(policy, make_batch(preset, policy.config, device), device)
    for _ in range(3):
        trainer.step()
    sampler.running = False
    sampler.join()
    print(torch.cuda.max_memory_allocated() if device.startswith("cuda") else sampler.peak - baseline)


def measure_memory(preset_name: str, device: str) -> dict[str, int]:
    peaks = {}
    for method in ("dp", "pacdp"):
        out = subprocess.run(
            [sys.executable, __file__, "--memory-child", method, "--preset", preset_name, "--device", device,
             "--batch-size", str(PRESETS[preset_name].batch_size)],
            capture_output=True, text=True, check=True,
        )
        peaks[f"{method}_peak_bytes"] = int(out.stdout.strip().splitlines()[-1])
    return peaks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch-size", type=int, help="override the preset's batch size")
    parser.add_argument("--train-steps", type=int, help="override the preset's timed training steps per method")
    parser.add_argument("--latency-calls", type=int, help="override the preset's timed action chunks per method")
    parser.add_argument("--memory-child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    overrides = {"batch_size": args.batch_size, "train_steps": args.train_steps, "latency_calls": args.latency_calls}
    overrides = {k: v for k, v in overrides.items() if v}
    PRESETS[args.preset] = dataclasses.replace(PRESETS[args.preset], **overrides)
    if args.memory_child:
        peak_memory_child(args.memory_child, args.preset, args.device)
        return

    preset = PRESETS[args.preset]
    times = measure_times(preset, args.device)
    memory = measure_memory(args.preset, args.device)
    ratios = {
        "train_step": times["pacdp_step_s"] / times["dp_step_s"],
        "mean_mode_latency": times["pacdp_mean_chunk_s"] / times["dp_chunk_s"],
        "sample_mode_latency": times["pacdp_sample_chunk_s"] / times["dp_chunk_s"],
        "peak_memory": memory["pacdp_peak_bytes"] / memory["dp_peak_bytes"],
    }
    device_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"
    result = {
        "preset": args.preset,
        "config": preset.__dict__,
        "device": device_name,
        "torch": torch.__version__,
        "seconds": times,
        "memory_bytes": memory,
        "ratios_pacdp_over_dp": ratios,
        "targets": {"train_step": 1.3, "mean_mode_latency": 1.05},
    }
    print(f"PAC-DP vs DP, preset={args.preset}, device={device_name}, down_dims={preset.down_dims}, batch={preset.batch_size}")
    print(f"{'metric':<22}{'DP':>12}{'PAC-DP':>12}{'ratio':>8}{'target':>8}")
    print(f"{'train step (ms)':<22}{times['dp_step_s']*1e3:>12.1f}{times['pacdp_step_s']*1e3:>12.1f}{ratios['train_step']:>8.2f}{'<=1.30':>8}")
    print(f"{'mean-mode chunk (ms)':<22}{times['dp_chunk_s']*1e3:>12.1f}{times['pacdp_mean_chunk_s']*1e3:>12.1f}{ratios['mean_mode_latency']:>8.2f}{'<=1.05':>8}")
    print(f"{'sample-mode chunk (ms)':<22}{times['dp_chunk_s']*1e3:>12.1f}{times['pacdp_sample_chunk_s']*1e3:>12.1f}{ratios['sample_mode_latency']:>8.2f}{'':>8}")
    print(f"{'peak memory (MiB)':<22}{memory['dp_peak_bytes']/2**20:>12.1f}{memory['pacdp_peak_bytes']/2**20:>12.1f}{ratios['peak_memory']:>8.2f}{'':>8}")
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    out = RESULTS_DIR / f"speed_{args.preset}_b{preset.batch_size}_{'cuda' if args.device.startswith('cuda') else 'cpu'}.json"
    write_text_atomic(out, json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
