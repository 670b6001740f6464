"""The least the Bayesian layers can add to a training step and to a sample-mode chunk with torch's CPU operators,
beside what they add today (issue 12's targets: train step <= 1.15x the twin, sample-mode chunk <= 1.10x).

    OMP_NUM_THREADS=1 python benchmarks/bayesian_floor.py --threads 1    # CPU preset U-Net, batch 64

On the PAC-DP policy's own Bayesian tensors (every mu / rho pair of the U-Net), it times the per-weight work that
any implementation of Eq. 6 and of training rho must do, one torch operator per pass:

- draw: xi ~ N(0, I), one Gaussian per weight (`normal_` into a kept buffer);
- sigma: softplus(rho), one per weight (Eq. 7);
- sample: w = mu + sigma * xi (one `addcmul`);
- rho gradient: dL/drho = dL/dw * xi * sigmoid(rho) (sigmoid, then one `mul` with the product of the other two);
- optimizer, EMA and clipping over rho: torch's fused Adam step, the EMA's `_foreach_lerp_`, the gradient norm.

The KL and its gradient (at least two more passes) are left out, so the sums are strict lower bounds. The
training floor is the twin's step plus all of the above; the sample-mode floor is a mean-mode chunk plus draw
and sample (sigma is cached between chunks). Twin and PAC-DP steps and both chunk modes are timed in the same
rounds, interleaved; every number is a median of this process's CPU time. Writes
benchmarks/results/bayesian_floor_<preset>_b<batch>_cpu.json.
"""

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.bayesian_layers import bayesian_layers
from lerobot_pacdp.speed_benchmark import PRESETS, TARGETS, Trainer, build, make_batch

WARMUP = 2


def _cpu_seconds(fn: Callable[[], object]) -> float:
    started = time.process_time()
    fn()
    return time.process_time() - started


@torch.no_grad()
def _act(policy: torch.nn.Module, observation: dict[str, torch.Tensor]) -> None:
    """One action chunk in eval mode, then back to training mode (the mean-mode policy is also the trained one)."""
    policy.eval()
    policy.predict_action_chunk(observation)
    policy.train()


class PerWeightWork:
    """The floor's passes over the (mu, rho) tensors of one policy, each timed on its own."""

    def __init__(self, policy: torch.nn.Module):
        pairs = [(getattr(layer, name), getattr(layer, f"{name}_rho"))
                 for layer in bayesian_layers(policy.unet) for name in layer._bayesian_param_names()]  # fmt: skip
        self.mu = [mu.detach().clone() for mu, _ in pairs]
        self.rho = [torch.nn.Parameter(rho.detach().clone()) for _, rho in pairs]
        self.xi = [torch.empty_like(mu) for mu in self.mu]
        self.grad_w = [torch.randn_like(mu) for mu in self.mu]
        for rho in self.rho:
            rho.grad = torch.randn_like(rho)
        self.ema = [rho.detach().clone() for rho in self.rho]
        self.optimizer = torch.optim.Adam(self.rho, lr=1e-4, fused=True)
        self.sigma = [F.softplus(rho.detach()) for rho in self.rho]
        self.elements = sum(mu.numel() for mu in self.mu)

    def passes(self) -> dict[str, Callable[[], object]]:
        return {
            "draw": lambda: [xi.normal_() for xi in self.xi],
            "sigma": lambda: [F.softplus(rho.detach()) for rho in self.rho],
            "sample": lambda: [torch.addcmul(mu, sigma, xi) for mu, sigma, xi in zip(self.mu, self.sigma, self.xi, strict=True)],
            "rho_gradient": lambda: [torch.sigmoid(rho.detach()).mul_(torch.mul(g, xi))
                                     for rho, g, xi in zip(self.rho, self.grad_w, self.xi, strict=True)],
            "optimizer": self.optimizer.step,
            "ema": lambda: torch._foreach_lerp_(self.ema, [rho.detach() for rho in self.rho], 1e-3),
            "clip_norm": lambda: torch.linalg.vector_norm(torch.stack(torch._foreach_norm([r.grad for r in self.rho]))),
        }  # fmt: skip


TRAIN_FLOOR = ("draw", "sigma", "sample", "rho_gradient", "optimizer", "ema", "clip_norm")
CHUNK_FLOOR = ("draw", "sample")


def measure(preset_name: str, batch_size: int | None, down_dims: tuple[int, ...] | None, rounds: int) -> dict:
    preset = PRESETS[preset_name]
    overrides = {k: v for k, v in {"batch_size": batch_size, "down_dims": down_dims}.items() if v}
    preset = type(preset)(**{**preset.__dict__, **overrides})
    trainers = {m: Trainer(p := build(m, preset, "cpu"), make_batch(preset, p.config, "cpu"), "cpu") for m in ("twin", "pacdp")}
    acting = {"mean": trainers["pacdp"].policy, "sample": build("pacdp-sample", preset, "cpu")}
    acting["sample"].load_state_dict(acting["mean"].state_dict())
    observation = {k: v[:1] for k, v in trainers["twin"].batch.items() if k.startswith("observation")}
    work = PerWeightWork(trainers["pacdp"].policy)
    samples: dict[str, list[float]] = {}
    for round_index in range(rounds + WARMUP):
        timed = {f"{m}_step_s": trainer.step for m, trainer in trainers.items()}
        timed.update({f"{mode}_chunk_s": partial(_act, policy, observation) for mode, policy in acting.items()})
        timed.update({f"{name}_s": fn for name, fn in work.passes().items()})
        for name, fn in timed.items():
            seconds = _cpu_seconds(fn)
            if round_index >= WARMUP:
                samples.setdefault(name, []).append(seconds)
    s = {name: statistics.median(values) for name, values in samples.items()}
    train_floor = sum(s[f"{name}_s"] for name in TRAIN_FLOOR)
    chunk_floor = sum(s[f"{name}_s"] for name in CHUNK_FLOOR)
    return {
        "preset": preset_name,
        "config": {"down_dims": list(preset.down_dims), "batch_size": preset.batch_size},
        "bayesian_elements": work.elements,
        "cpu_seconds": s,
        "cpu_seconds_per_round": samples,
        "train_step": {"twin_s": s["twin_step_s"], "pacdp_s": s["pacdp_step_s"], "floor_extra_s": train_floor,
                       "measured_over_twin": s["pacdp_step_s"] / s["twin_step_s"],
                       "floor_over_twin": (s["twin_step_s"] + train_floor) / s["twin_step_s"]},
        "sample_mode_chunk": {"mean_mode_s": s["mean_chunk_s"], "sample_mode_s": s["sample_chunk_s"],
                              "floor_extra_s": chunk_floor,
                              "measured_over_mean_mode": s["sample_chunk_s"] / s["mean_chunk_s"],
                              "floor_over_mean_mode": (s["mean_chunk_s"] + chunk_floor) / s["mean_chunk_s"]},
        "targets": TARGETS.get((preset_name, "cpu"), {}),
    }  # fmt: skip


def print_table(result: dict) -> None:
    s, step, chunk, targets = result["cpu_seconds"], result["train_step"], result["sample_mode_chunk"], result["targets"]
    print(f"Bayesian floor, preset={result['preset']}, {result['config']}, {result['bayesian_elements']:,} Bayesian elements")
    for name in TRAIN_FLOOR:
        print(f"  {name:<14}{s[f'{name}_s'] * 1e3:8.2f} ms" + ("  (chunk floor)" if name in CHUNK_FLOOR else ""))
    print(f"{'':<24}{'twin/mean':>10}{'PAC-DP':>10}{'measured':>10}{'floor':>8}{'target':>8}")
    for label, base, value, measured, floor, key in (
        ("train step (ms)", step["twin_s"], step["pacdp_s"], step["measured_over_twin"], step["floor_over_twin"], "train_step"),
        ("sample-mode chunk (ms)", chunk["mean_mode_s"], chunk["sample_mode_s"], chunk["measured_over_mean_mode"],
         chunk["floor_over_mean_mode"], "sample_mode_latency"),
    ):  # fmt: skip
        target = f"<={targets[key]:.2f}" if key in targets else ""
        print(f"{label:<24}{base * 1e3:>10.1f}{value * 1e3:>10.1f}{measured:>10.2f}{floor:>8.2f}{target:>8}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    parser.add_argument("--batch-size", type=int, help="override the preset's batch size")
    parser.add_argument("--down-dims", type=int, nargs="+", help="override the preset's U-Net widths")
    parser.add_argument("--rounds", type=int, default=15, help=f"timed rounds (after {WARMUP} warm-up rounds)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    parser.add_argument("--output", type=Path, help="the JSON (default benchmarks/results/bayesian_floor_<preset>_b<batch>_cpu.json)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    result = measure(args.preset, args.batch_size, tuple(args.down_dims) if args.down_dims else None, args.rounds)
    result["device"] = f"CPU ({platform.processor() or platform.machine()}, {args.threads} threads)"
    result["torch"] = torch.__version__
    result["machine_load"] = {"loadavg_1_5_15_before": load_before, "loadavg_1_5_15_after": os.getloadavg()}
    print_table(result)
    output = args.output or Path(__file__).parent / "results" / (
        f"bayesian_floor_{args.preset}_b{result['config']['batch_size']}_cpu.json"
    )
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(output, json.dumps(result, indent=2))
    print(f"wrote {output}")


if __name__ == "__main__":
    main()
