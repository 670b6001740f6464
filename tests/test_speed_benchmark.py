"""benchmarks/speed.py, the script behind the README's performance rows and the prepared GPU command."""

import dataclasses
import json
import math
import os
import subprocess
import sys

import pytest

from lerobot_pacdp.speed_benchmark import PRESETS, build

from pacdp_testing import REPO_ROOT


@pytest.mark.slow
def test_speed_benchmark_prints_the_ratio_table_and_writes_consistent_json(tmp_path):
    command = [sys.executable, str(REPO_ROOT / "benchmarks" / "speed.py"), "--preset", "cpu", "--down-dims", "8", "16",
               "--batch-size", "2", "--train-steps", "2", "--latency-calls", "1", "--threads", "1",
               "--output-dir", str(tmp_path), "--note", "test run"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    table = result.stdout
    for row in ("train step (ms)", "mean-mode chunk (ms)", "sample-mode chunk (ms)", "peak memory (MiB)", "in CPU time"):
        assert row in table
    [written] = list(tmp_path.iterdir())
    assert written.name == "speed_cpu_b2_cpu.json"
    data = json.loads(written.read_text())
    s, rounds, m = data["seconds"], data["seconds_per_round"], data["memory_bytes"]
    assert data["config"]["down_dims"] == [8, 16] and data["machine_load"]["note"] == "test run"
    assert data["command"] == ("python benchmarks/speed.py --preset cpu --device cpu --threads 1 --batch-size 2 "
                               "--train-steps 2 --latency-calls 1 --down-dims 8 16")
    assert all(len(v) == 2 for v in [rounds["dp_step_s"], rounds["twin_step_s"], rounds["pacdp_step_s"]])
    assert s["dp_step_s"] == pytest.approx(sum(rounds["dp_step_s"]) / 2)  # the median of two rounds

    def paired(a, b):  # the median over rounds of the per-round ratio (two rounds: their mean)
        return sum(x / y for x, y in zip(rounds[a], rounds[b], strict=True)) / len(rounds[a])

    assert data["ratios_pacdp_over_dp"]["train_step"] == pytest.approx(paired("pacdp_step_s", "dp_step_s"))
    assert data["ratios_pacdp_over_twin"]["train_step"] == pytest.approx(paired("pacdp_step_s", "twin_step_s"))
    assert data["ratios_pacdp_over_dp"]["mean_mode_latency"] == pytest.approx(
        rounds["pacdp_mean_chunk_s"][0] / rounds["dp_chunk_s"][0]
    )
    assert data["ratios_pacdp_over_twin"]["peak_memory"] == pytest.approx(m["pacdp_peak_bytes"] / m["twin_peak_bytes"])
    assert all(v > 0 and math.isfinite(v) for v in [*s.values(), *m.values(), *data["cpu_seconds"].values()])
    assert data["targets"]["train_step"] == 1.15


def test_bayesian_floor_sums_the_per_weight_passes_and_compares_them_with_the_measured_overhead(tmp_path):
    output = tmp_path / "floor.json"
    command = [sys.executable, str(REPO_ROOT / "benchmarks" / "bayesian_floor.py"), "--down-dims", "8", "16",
               "--batch-size", "2", "--rounds", "3", "--threads", "1", "--output", str(output)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "train step (ms)" in result.stdout and "sample-mode chunk (ms)" in result.stdout
    data = json.loads(output.read_text())
    s, rounds, step, chunk = data["cpu_seconds"], data["cpu_seconds_per_round"], data["train_step"], data["sample_mode_chunk"]
    passes = ("draw", "sigma", "sample", "rho_gradient", "optimizer", "ema", "clip_norm")
    assert all(len(rounds[f"{name}_s"]) == 3 and s[f"{name}_s"] == sorted(rounds[f"{name}_s"])[1] for name in passes)
    assert step["floor_extra_s"] == pytest.approx(sum(s[f"{name}_s"] for name in passes))
    assert step["floor_over_twin"] == pytest.approx(1 + step["floor_extra_s"] / s["twin_step_s"])
    assert chunk["floor_extra_s"] == pytest.approx(s["draw_s"] + s["sample_s"])
    assert chunk["measured_over_mean_mode"] == pytest.approx(s["sample_chunk_s"] / s["mean_chunk_s"])
    policy = build("pacdp", dataclasses.replace(PRESETS["cpu"], down_dims=(8, 16), batch_size=2), "cpu")
    rho_elements = sum(p.numel() for name, p in policy.unet.named_parameters() if name.endswith("_rho"))
    assert data["bayesian_elements"] == rho_elements  # one mu/rho pair per Bayesian weight and bias
    assert all(v > 0 and math.isfinite(v) for v in s.values())
    assert data["targets"] == {"train_step": 1.15, "peak_memory": 2.0, "sample_mode_latency": 1.10, "mean_mode_latency": 1.00}
