"""benchmarks/uncertainty_latency.py, the script behind the README's latency of K = 8 against one chunk."""

import json
import os
import subprocess
import sys

from pacdp_testing import REPO_ROOT


def test_the_latency_benchmark_times_every_variant_and_writes_its_command(tmp_path):
    output = tmp_path / "latency.json"
    command = [sys.executable, str(REPO_ROOT / "benchmarks" / "uncertainty_latency.py"), "--rounds", "1",
               "--batch-sizes", "1", "--samples", "2", "--output", str(output)]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    data = json.loads(output.read_text())
    assert data["command"].endswith("--threads 1 --batch-sizes 1 --samples 2 --rounds 1") and data["samples"] == 2
    timings = data["results"]["batch_1"]
    names = {"one_chunk", "posterior_k_batched", "posterior_k_sequential", "noise_k_batched", "predict_with_uncertainty"}
    assert set(timings["median"]) == names and timings["cpu_time_over_one_chunk"]["one_chunk"] == 1.0
    assert all(m["wall_s"] > 0 and m["cpu_s"] > 0 for m in timings["median"].values())
