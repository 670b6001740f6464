"""`pacdp-study --train=false` regenerates the committed results (results/study_cpu_pusht*) from their metrics files.

The runs' checkpoints are long gone; what is committed is each seed's `metrics.json` (as `metrics_seed<k>.json`)
and the per-run success rates (in `runs.csv`; a study keeps them in `success.json` beside `metrics.json`).
"""

import csv
import json
import shutil
from pathlib import Path

import pytest

from lerobot_pacdp.study import runner
from lerobot_pacdp.study.evidence import METHODS
from lerobot_pacdp.study.presets import get_preset

from pacdp_testing import REPO_ROOT

RESULTS = REPO_ROOT / "results"


def _study_from_committed(committed: Path, out: Path, group: str) -> None:
    """The output dir of a study whose checkpoints were deleted: its metrics and success-rate files only."""
    env = get_preset("cpu").tasks[0].train_config["env"]
    runs = {row["name"]: row for row in csv.DictReader((committed / "runs.csv").open())}
    for metrics_file in sorted(committed.glob("metrics_seed*.json")):
        seed_dir = out / "metrics" / group / "pusht" / metrics_file.stem.removeprefix("metrics_")
        seed_dir.mkdir(parents=True)
        shutil.copy(metrics_file, seed_dir / "metrics.json")
        rows = json.loads(metrics_file.read_text())["rows"]
        last = {}  # the cpu preset rolls out each run's last checkpoint only
        for row in sorted(rows, key=lambda r: r["step"]):
            last[row["label"]] = row["checkpoint"]
        rates = {checkpoint: float(runs[name]["success_rate"]) for name, checkpoint in last.items()}
        success = {"settings": {"episodes": 10, "seed": 0, "env": env}, "rates": rates}
        (seed_dir / "success.json").write_text(json.dumps(success))


def _until_performance(markdown: str) -> str:
    """tables.md without its performance section (measured separately, by the speed benchmark)."""
    return markdown.split("## Performance")[0]


@pytest.mark.parametrize(
    ("committed", "group", "flags"),
    [("study_cpu_pusht", "main", []), ("study_cpu_pusht_long", "long", ["--long_pair=true", "--report_unfinished=true"])],
)
def test_the_committed_tables_regenerate_from_their_metrics_files(tmp_path, pusht_zarr, committed, group, flags):
    committed = RESULTS / committed
    _study_from_committed(committed, tmp_path, group)
    argv = ["--preset=cpu", f"--output_dir={tmp_path}", f"--pusht_zarr={pusht_zarr}", "--train=false", *flags]
    assert runner.main(argv) == 0
    results = tmp_path / ("results_long" if group == "long" else "results")
    for name in ("runs.csv", "dynamics.csv", "tables.csv"):
        assert (results / name).read_text() == (committed / name).read_text(), name
    assert _until_performance((results / "tables.md").read_text()) == _until_performance(
        (committed / "tables.md").read_text()
    )
    assert {p.name for p in (results / "figures").iterdir()} == {p.name for p in (committed / "figures").iterdir()}


@pytest.mark.parametrize(
    ("study", "flags"),
    [
        ("study_cpu_v2", []),
        # benchmarks/study_cpu_v2.sh with STEPS=6000 SUCCESS_EVERY=2000 (20 and 40 demos)
        ("study_cpu_v2_steps6000", ["--steps=6000", "--save_freq=1000", "--success_every=2000"]),
        # STEPS=12000 SUCCESS_EVERY=4000 (20 and 40 demos)
        ("study_cpu_v2_steps12000", ["--steps=12000", "--save_freq=1000", "--success_every=4000"]),
        # STEPS=24000 SUCCESS_EVERY=8000 DEMOS=20
        ("study_cpu_v2_steps24000", ["--steps=24000", "--save_freq=1000", "--success_every=8000"]),
        # STEPS=40000 SUCCESS_EVERY=10000 DEMOS=20 (Can)
        ("study_cpu_v2_steps40000", ["--steps=40000", "--save_freq=1000", "--success_every=10000"]),
        # STEPS=60000 SUCCESS_EVERY=10000 (Can: seeds 0, 1 and 2 with 20 and with 40 demos)
        ("study_cpu_v2_steps60000", ["--steps=60000", "--save_freq=1000", "--success_every=10000"]),
        # STEPS=80000 SUCCESS_EVERY=10000 DEMOS=20 (Can, seeds 0, 1 and 2: does PAC-DP's plateau hold)
        ("study_cpu_v2_steps80000", ["--steps=80000", "--save_freq=1000", "--success_every=10000"]),
        # STEPS=120000 SUCCESS_EVERY=10000 DEMOS=20 METHODS=PAC-DP (Can, seed 0: PAC-DP's plateau)
        ("study_cpu_v2_steps120000",
         ["--steps=120000", "--save_freq=1000", "--success_every=10000", "--methods=[PAC-DP]"]),
    ],
)
def test_the_committed_evidence_study_regenerates_from_its_metrics_and_success_files(tmp_path, request, study, flags):
    """results/study_cpu_v2* commit each (task, seed)'s metrics.json and success.json as the study keeps them;
    `--published_metrics` brings them into an empty output dir (PushT's held-out split needs its demos)."""
    committed = RESULTS / study
    tasks = sorted(p.name for p in (committed / "metrics" / "main").iterdir())
    if "pusht" in tasks:
        flags = [*flags, f"--pusht_zarr={request.getfixturevalue('pusht_zarr')}"]
    argv = ["--preset=cpu_v2", f"--output_dir={tmp_path}", f"--tasks=[{','.join(tasks)}]", "--train=false",
            f"--published_metrics={committed / 'metrics'}", *flags]  # fmt: skip
    assert runner.main(argv) == 0
    for name in ("summary.json", "paired.json", "evidence.md", "runs.csv", "dynamics.csv", "tables.csv"):
        assert (tmp_path / "results" / name).read_text() == (committed / name).read_text(), name
    rows = json.loads((committed / "summary.json").read_text())
    only = [f.removeprefix("--methods=[").rstrip("]").split(",") for f in flags if f.startswith("--methods=")]
    methods = only[0] if only else METHODS
    assert {r["method"] for r in rows} == set(methods)
    assert all(r["n_episodes"] >= 50 and r["success_rate"] is not None for r in rows)
