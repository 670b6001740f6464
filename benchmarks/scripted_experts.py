"""Success rate, episode length and wall time of the scripted Lift/Can/Square experts.

Runs each expert for N seeded episodes (robosuite 1.5, robomimic settings) without and with action
noise, prints a table and writes benchmarks/results/scripted_experts.json (with the machine's load average,
since wall times on a shared machine depend on it).

    python benchmarks/scripted_experts.py --episodes 50 [--tasks lift can square] [--noise 0 0.05]
"""

import argparse
import json
import os
import platform
import sys
from pathlib import Path

from lerobot_pacdp.robomimic.scripted_experts import EXPERTS, measure_success_rate


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--tasks", nargs="+", default=list(EXPERTS))
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.05])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "scripted_experts.json")
    args = parser.parse_args(argv)

    rows = []
    for task in args.tasks:
        for noise in args.noise:
            load_before = os.getloadavg()[0]
            stats = measure_success_rate(task, args.episodes, seed=args.seed, action_noise=noise)
            # Wall times depend on the machine's load: record it (1-minute load average, before / after).
            load = [round(load_before, 2), round(os.getloadavg()[0], 2)]
            row = {**stats.as_dict(), "action_noise": noise, "seed": args.seed, "load_average": load}
            rows.append(row)
            print(
                f"{task:7s} noise={noise:<5} success {stats.successes}/{stats.attempts} ({stats.success_rate:.0%})  "
                f"mean length {row['mean_success_length'] or float('nan'):.0f} steps  "
                f"{row['seconds_per_attempt']:.2f} s/episode",
                flush=True,
            )
    import robosuite

    result = {
        "episodes_per_setting": args.episodes,
        "robosuite": robosuite.__version__,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU threads",
        "results": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
