"""lerobot-train's data time with LeRobot's data path against the in-memory one, measured in one run.

Trains the same config twice per round, `PACDP_IN_MEMORY_DATA=0` (LeRobotDataset's per-item queries) and
`=1` (lerobot_pacdp.in_memory_data), alternating for `--rounds` rounds, and reads LeRobot's own per-step
timings from its log (`updt_s`, `data_s`, averaged over each log window; the first window, which holds the
warm-up, is dropped). Prints the table and writes benchmarks/results/data_path_<name>.json.

    python benchmarks/data_path.py --dataset-root outputs/main_job_lift/data --name lift_cpu
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from lerobot_pacdp.atomic_io import write_text_atomic  # noqa: E402

TIMINGS = re.compile(r"updt_s:(?P<update>[0-9.]+) data_s:(?P<data>[0-9.]+)")


def train_timings(args: argparse.Namespace, in_memory: bool, output_dir: Path) -> dict:
    command = [
        str(Path(sys.executable).parent / "lerobot-train"), f"--config_path={args.config}",
        f"--dataset.root={args.dataset_root}", f"--steps={args.steps}", f"--log_freq={args.log_freq}",
        f"--batch_size={args.batch_size}", "--save_checkpoint=false", "--eval_steps=0", "--wandb.enable=false",
        f"--output_dir={output_dir}",
    ]  # fmt: skip
    env = {**os.environ, "PACDP_IN_MEMORY_DATA": "1" if in_memory else "0", "HF_HUB_OFFLINE": "1"}
    env["OMP_NUM_THREADS"] = str(args.threads)
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, env=env)
    if result.returncode != 0:
        raise SystemExit(f"lerobot-train failed:\n{result.stderr[-3000:]}")
    windows = [(float(m["update"]), float(m["data"])) for m in TIMINGS.finditer(result.stdout + result.stderr)][1:]
    if not windows:
        raise SystemExit("no timing lines in lerobot-train's log; raise --steps or lower --log_freq")
    update = statistics.mean(w[0] for w in windows)
    data = statistics.mean(w[1] for w in windows)
    return {"update_s": update, "data_s": data, "steps_per_s": 1.0 / (update + data), "data_share": data / (update + data),
            "wall_s": time.perf_counter() - start}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=str(REPO / "configs/robomimic/lift_cpu.json"))
    parser.add_argument("--dataset-root", required=True)
    parser.add_argument("--name", default="lift_cpu")
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--log-freq", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--note", default="")
    args = parser.parse_args()

    runs: dict[str, list[dict]] = {"lerobot": [], "in_memory": []}
    with tempfile.TemporaryDirectory() as tmp:
        for round_index in range(args.rounds):
            for name, in_memory in (("lerobot", False), ("in_memory", True)):
                runs[name].append(train_timings(args, in_memory, Path(tmp) / f"{name}{round_index}"))
                print(f"round {round_index} {name}: {runs[name][-1]}", flush=True)
    median = {name: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for name, rs in runs.items()}
    speedup = median["in_memory"]["steps_per_s"] / median["lerobot"]["steps_per_s"]
    print("\n| data path | update s/step | data s/step | data share | steps/s |\n|---|---|---|---|---|")
    for name, m in median.items():
        print(f"| {name} | {m['update_s']:.3f} | {m['data_s']:.3f} | {100 * m['data_share']:.1f}% | {m['steps_per_s']:.2f} |")
    print(f"in-memory / LeRobot steps/s: {speedup:.2f}x")
    result = {"config": args.config, "batch_size": args.batch_size, "steps": args.steps, "threads": args.threads,
              "rounds": args.rounds, "runs": runs, "median": median, "speedup_steps_per_s": speedup, "note": args.note}  # fmt: skip
    out = REPO / "benchmarks" / "results" / f"data_path_{args.name}.json"
    write_text_atomic(out, json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
