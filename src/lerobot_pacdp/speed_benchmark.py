"""PAC-DP's cost against DP on the same U-Net, batch and data: training step, action-chunk latency, peak memory.

Three policies train on one fixed batch through LeRobot's own `update_policy` (forward, backward, gradient
clipping, the optimizer its preset builds, the policy's `update()`), as `lerobot-train` runs them:

- `dp`: LeRobot's `diffusion` policy with PAC-DP's diffusion settings (`PacdpConfig.diffusion_twin`);
- `twin`: PAC-DP with `bayesian=false` (the same policy code and EMA, deterministic layers);
- `pacdp`: PAC-DP (Bayesian U-Net, Eq. 9).

pacdp/twin is the Bayesian overhead alone; pacdp/dp is what moving from LeRobot's `diffusion` costs (the EMA
included). Timings alternate between the policies in one process, round by round, so background load hits
all alike: the table shows median seconds, and each ratio is the median over rounds of that round's ratio.
Peak memory is measured per policy in a fresh subprocess (CPU: peak resident-memory growth over the run,
sampled every millisecond; CUDA: torch.cuda.max_memory_allocated). Prints a table and writes JSON to
benchmarks/results/ (the checkout's `benchmarks/speed.py` runs this module), or `run_benchmark` from Python.

    python benchmarks/speed.py --preset cpu --threads 2                    # 2 CPU cores, CPU-preset U-Net
    python benchmarks/speed.py --preset paper --batch-size 64 --threads 2  # paper U-Net on 2 CPU cores
    python benchmarks/speed.py --preset paper --device cuda --batch-size 256  # the GPU row
"""

import argparse
import dataclasses
import json
import os
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
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.modeling_pacdp import PacdpPolicy

STATE_DIM, ENV_DIM, ACTION_DIM = 2, 16, 2  # PushT, state-based
WARMUP = 3
TRAINED = ("dp", "twin", "pacdp")
ACTING = ("dp", "pacdp", "pacdp-sample")


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



@dataclasses.dataclass(frozen=True)
class BenchmarkRequest:
    """One benchmark run: a U-Net preset on a device, with optional overrides of the preset's sizes."""

    preset: str
    device: str
    output_dir: Path  # where the JSON goes
    threads: int = dataclasses.field(default_factory=torch.get_num_threads)  # torch intra-op threads
    batch_size: int | None = None
    train_steps: int | None = None  # timed training steps per policy
    latency_calls: int | None = None  # timed action chunks per policy
    down_dims: tuple[int, ...] | None = None
    note: str = ""  # what else ran on the machine, recorded in the JSON

    def sizes(self) -> Preset:
        overrides = {"batch_size": self.batch_size, "train_steps": self.train_steps,
                     "latency_calls": self.latency_calls, "down_dims": self.down_dims}  # fmt: skip
        return dataclasses.replace(PRESETS[self.preset], **{k: v for k, v in overrides.items() if v})

    def result_file(self) -> Path:
        kind = "cuda" if self.device.startswith("cuda") else "cpu"
        return self.output_dir / f"speed_{self.preset}_b{self.sizes().batch_size}_{kind}.json"


# Issue 12's targets for PAC-DP/DP, by (preset, device kind).
TARGETS = {
    ("cpu", "cpu"): {"train_step": 1.15, "peak_memory": 2.0, "sample_mode_latency": 1.10, "mean_mode_latency": 1.00},
    ("paper", "cpu"): {"train_step": 1.5},
    ("paper", "cuda"): {"train_step": 1.10},
}


def _features():
    inputs = {
        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (ENV_DIM,)),
    }
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}


def build(method: str, preset: Preset, device: str) -> torch.nn.Module:
    """The same diffusion settings for every method; only what the method name says differs."""
    config = PacdpConfig(
        down_dims=preset.down_dims,
        diffusion_step_embed_dim=preset.step_embed_dim,
        num_train_samples=25_650,
        device=device,
        bayesian=method != "twin",
        inference_mode="sample" if method == "pacdp-sample" else "mean",
    )
    if method == "dp":
        config = config.diffusion_twin()
    config.input_features, config.output_features = _features()
    torch.manual_seed(0)
    return (DiffusionPolicy if method == "dp" else PacdpPolicy)(config).to(device)


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
    """One lerobot-train update per `step()`: LeRobot's `update_policy` with the policy's optimizer preset."""

    def __init__(self, policy, batch, device):
        from accelerate import Accelerator
        from lerobot.scripts.lerobot_train import update_policy
        from lerobot.utils.logging_utils import AverageMeter, MetricsTracker

        self.policy, self.batch, self.device, self._update_policy = policy, batch, device, update_policy
        optimizer_config = policy.config.get_optimizer_preset()
        self.optimizer = optimizer_config.build(policy.get_optim_params())
        self.grad_clip_norm = optimizer_config.grad_clip_norm
        self.accelerator = Accelerator(cpu=not device.startswith("cuda"))
        meters = {
            name: AverageMeter(name, ":.3f") for name in ("loss", "grad_norm", "lr", "update_s", "dataloading_s")
        }
        self.metrics = MetricsTracker(len(batch["action"]), 10**6, 10**3, meters)

    def step(self) -> tuple[float, float]:
        return _timed(self.device, self._update_policy, self.metrics, self.policy, self.batch, self.optimizer,
                      self.grad_clip_norm, self.accelerator)


def _timed(device: str, fn, *args) -> tuple[float, float]:
    """(wall seconds, this process's CPU seconds) of one call; CPU time is what contention inflates least."""
    _sync(device)
    wall, cpu = time.perf_counter(), time.process_time()
    fn(*args)
    _sync(device)
    return time.perf_counter() - wall, time.process_time() - cpu


def chunk_latency(policy, batch, device) -> tuple[float, float]:
    obs = {k: v[:1] for k, v in batch.items() if k.startswith("observation")}
    policy.eval()
    return _timed(device, policy.predict_action_chunk, obs)


def measure_times(preset: Preset, device: str) -> dict[str, dict[str, list[float]]]:
    """Wall and CPU seconds of every timed training step and action chunk, the methods interleaved round by round."""
    trainers = {}
    for method in TRAINED:
        policy = build(method, preset, device)
        trainers[method] = Trainer(policy, make_batch(preset, policy.config, device), device)
    steps: dict[str, list[tuple[float, float]]] = {m: [] for m in TRAINED}
    for i in range(preset.train_steps + WARMUP):
        for method, trainer in trainers.items():
            timing = trainer.step()
            if i >= WARMUP:
                steps[method].append(timing)
    acting = {"dp": trainers["dp"].policy, "pacdp": trainers["pacdp"].policy}
    acting["pacdp-sample"] = build("pacdp-sample", preset, device)
    acting["pacdp-sample"].load_state_dict(acting["pacdp"].state_dict())
    batch = trainers["dp"].batch
    chunks: dict[str, list[tuple[float, float]]] = {m: [] for m in ACTING}
    with torch.no_grad():
        for i in range(preset.latency_calls + WARMUP):
            for method, policy in acting.items():
                timing = chunk_latency(policy, batch, device)
                if i >= WARMUP:
                    chunks[method].append(timing)
    names = {"dp": "dp_chunk_s", "pacdp": "pacdp_mean_chunk_s", "pacdp-sample": "pacdp_sample_chunk_s"}
    return {
        clock: {
            **{f"{m}_step_s": [t[index] for t in steps[m]] for m in TRAINED},
            **{names[m]: [t[index] for t in chunks[m]] for m in ACTING},
        }
        for index, clock in enumerate(("wall", "cpu"))
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


def peak_memory_child(method: str, preset: Preset, device: str) -> None:
    """Run in a subprocess: build the policy and train a few steps, then print the peak memory (bytes).

    CPU: peak resident memory during construction and training minus the resident memory before it
    (weights, gradients, optimizer state, EMA copy, activations). CUDA: peak allocated memory of the last
    step (LeRobot's `update_policy` resets the CUDA peak at each step).
    """
    baseline = psutil.Process().memory_info().rss
    sampler = _RssPeak()
    sampler.start()
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    policy = build(method, preset, device)
    trainer = Trainer(policy, make_batch(preset, policy.config, device), device)
    for _ in range(WARMUP):
        trainer.step()
    sampler.running = False
    sampler.join()
    print(torch.cuda.max_memory_allocated() if device.startswith("cuda") else sampler.peak - baseline)


def measure_memory(request: BenchmarkRequest) -> dict[str, int]:
    peaks, preset = {}, request.sizes()
    for method in TRAINED:
        command = [sys.executable, "-m", "lerobot_pacdp.speed_benchmark", "--memory-child", method, "--preset", request.preset,
                   "--device", request.device, "--batch-size", str(preset.batch_size), "--threads", str(request.threads),
                   "--down-dims", *map(str, preset.down_dims)]  # fmt: skip
        out = subprocess.run(command, capture_output=True, text=True, check=True)
        peaks[f"{method}_peak_bytes"] = int(out.stdout.strip().splitlines()[-1])
    return peaks


def medians(samples: dict[str, list[float]]) -> dict[str, float]:
    return {name: statistics.median(values) for name, values in samples.items()}


def paired_ratio(samples: dict[str, list[float]], numerator: str, denominator: str) -> float:
    """Median over rounds of numerator/denominator, each round's two runs back to back (load drift cancels)."""
    return statistics.median(a / b for a, b in zip(samples[numerator], samples[denominator], strict=True))


def ratios(samples: dict[str, list[float]], memory: dict[str, int]) -> dict[str, dict[str, float]]:
    """PAC-DP over each baseline; action chunks only against dp (the twin acts with the same network as dp)."""
    over_dp = {
        "train_step": paired_ratio(samples, "pacdp_step_s", "dp_step_s"),
        "mean_mode_latency": paired_ratio(samples, "pacdp_mean_chunk_s", "dp_chunk_s"),
        "sample_mode_latency": paired_ratio(samples, "pacdp_sample_chunk_s", "dp_chunk_s"),
        "peak_memory": memory["pacdp_peak_bytes"] / memory["dp_peak_bytes"],
    }
    over_twin = {
        "train_step": paired_ratio(samples, "pacdp_step_s", "twin_step_s"),
        "peak_memory": memory["pacdp_peak_bytes"] / memory["twin_peak_bytes"],
    }
    return {"ratios_pacdp_over_dp": over_dp, "ratios_pacdp_over_twin": over_twin}


def print_table(result: dict) -> None:
    s, m, targets = result["seconds"], result["memory_bytes"], result["targets"]
    over_dp, over_twin = result["ratios_pacdp_over_dp"], result["ratios_pacdp_over_twin"]
    print(f"PAC-DP vs DP, preset={result['preset']}, device={result['device']}, "
          f"down_dims={tuple(result['config']['down_dims'])}, batch={result['config']['batch_size']}")
    print(f"{'metric':<24}{'DP':>10}{'twin':>10}{'PAC-DP':>10}{'/DP':>8}{'/twin':>8}{'target':>8}")

    def row(label, key, dp, twin, pacdp, scale):
        twin_cell = f"{twin * scale:>10.1f}" if twin is not None else f"{'':>10}"
        twin_ratio = f"{over_twin[key]:>8.2f}" if key in over_twin else f"{'':>8}"
        target = f"<={targets[key]:.2f}" if key in targets else ""
        print(f"{label:<24}{dp * scale:>10.1f}{twin_cell}{pacdp * scale:>10.1f}{over_dp[key]:>8.2f}{twin_ratio}{target:>8}")

    row("train step (ms)", "train_step", s["dp_step_s"], s["twin_step_s"], s["pacdp_step_s"], 1e3)
    row("mean-mode chunk (ms)", "mean_mode_latency", s["dp_chunk_s"], None, s["pacdp_mean_chunk_s"], 1e3)
    row("sample-mode chunk (ms)", "sample_mode_latency", s["dp_chunk_s"], None, s["pacdp_sample_chunk_s"], 1e3)
    row("peak memory (MiB)", "peak_memory", m["dp_peak_bytes"], m["twin_peak_bytes"], m["pacdp_peak_bytes"], 2**-20)


def measurement_command(request: BenchmarkRequest) -> str:
    """The command that repeats this measurement (the flags that change what is measured)."""
    flags = ["--preset", request.preset, "--device", request.device, "--threads", str(request.threads)]
    for flag, value in (("--batch-size", request.batch_size), ("--train-steps", request.train_steps),
                        ("--latency-calls", request.latency_calls)):  # fmt: skip
        if value:
            flags += [flag, str(value)]
    if request.down_dims:
        flags += ["--down-dims", *map(str, request.down_dims)]
    return " ".join(["python", "benchmarks/speed.py", *flags])


def run_benchmark(request: BenchmarkRequest) -> dict:
    """Measure, print the table, write `request.result_file()` and return its content."""
    torch.set_num_threads(request.threads)
    preset = request.sizes()
    load_before = os.getloadavg()
    started = time.time()
    timings = measure_times(preset, request.device)
    memory = measure_memory(request)
    kind = "cuda" if request.device.startswith("cuda") else "cpu"
    device_name = (
        torch.cuda.get_device_name() if kind == "cuda"
        else f"CPU ({platform.processor() or platform.machine()}, {request.threads} threads)"
    )  # fmt: skip
    result = {
        "preset": request.preset,
        "config": dataclasses.asdict(preset),
        "device": device_name,
        "torch": torch.__version__,
        "command": measurement_command(request),
        "seconds": medians(timings["wall"]),
        "seconds_per_round": timings["wall"],
        "memory_bytes": memory,
        **ratios(timings["wall"], memory),
        "targets": TARGETS.get((request.preset, kind), {}),
        "machine_load": {"loadavg_1_5_15_before": load_before, "loadavg_1_5_15_after": os.getloadavg(),
                         "wall_s": round(time.time() - started, 1), "note": request.note},
    }  # fmt: skip
    if kind == "cpu":  # the same medians in this process's CPU time (all threads): less inflated by other jobs
        result["cpu_seconds"] = medians(timings["cpu"])
        result["cpu_time_ratios"] = {
            k: {m: v for m, v in r.items() if m != "peak_memory"} for k, r in ratios(timings["cpu"], memory).items()
        }
    print_table(result)
    cpu = result.get("cpu_time_ratios")
    if cpu:
        print("in CPU time: train step /DP {:.2f} /twin {:.2f}, mean-mode chunk {:.2f}, sample-mode chunk {:.2f}".format(
            cpu["ratios_pacdp_over_dp"]["train_step"], cpu["ratios_pacdp_over_twin"]["train_step"],
            cpu["ratios_pacdp_over_dp"]["mean_mode_latency"], cpu["ratios_pacdp_over_dp"]["sample_mode_latency"]))  # fmt: skip
    request.output_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(request.result_file(), json.dumps(result, indent=2))
    print(f"wrote {request.result_file()}")
    return result


def main(argv: list[str] | None = None, default_output_dir: Path = Path("benchmarks/results")) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch-size", type=int, help="override the preset's batch size")
    parser.add_argument("--train-steps", type=int, help="override the preset's timed training steps per method")
    parser.add_argument("--latency-calls", type=int, help="override the preset's timed action chunks per method")
    parser.add_argument("--down-dims", type=int, nargs="+", help="override the preset's U-Net widths")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    parser.add_argument("--output-dir", type=Path, default=default_output_dir, help="where the JSON goes")
    parser.add_argument("--note", default="", help="what else ran on the machine, recorded in the JSON")
    parser.add_argument("--memory-child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    request = BenchmarkRequest(
        preset=args.preset, device=args.device, output_dir=args.output_dir, threads=args.threads,
        batch_size=args.batch_size, train_steps=args.train_steps, latency_calls=args.latency_calls,
        down_dims=tuple(args.down_dims) if args.down_dims else None, note=args.note,
    )  # fmt: skip
    if args.memory_child:
        torch.set_num_threads(request.threads)
        peak_memory_child(args.memory_child, request.sizes(), request.device)
        return
    run_benchmark(request)


if __name__ == "__main__":
    main()
