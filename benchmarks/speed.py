"""PAC-DP's cost against DP (training step, action-chunk latency, peak memory): `lerobot_pacdp.speed_benchmark`.

    python benchmarks/speed.py --preset cpu --threads 1    # results in benchmarks/results/
"""

from pathlib import Path

from lerobot_pacdp.speed_benchmark import main

if __name__ == "__main__":
    main(default_output_dir=Path(__file__).parent / "results")
