"""`--executor=slurm`: the job array through submitit, with submitit's local and debug executors standing in for
SLURM, and `--dry_run=true` printing each job's SLURM parameters."""

import dataclasses
import json
import sys
from pathlib import Path

import pytest

from lerobot_pacdp.study import runner, slurm
from lerobot_pacdp.study.plan import RunSpec, plan_task, train_config
from lerobot_pacdp.study.presets import Preset, get_preset
from lerobot_pacdp.study.slurm import SlurmExecutor, SlurmOptions
from lerobot_pacdp.study.state import DONE_FILE, JOB_FILE, REQUEST_FILE, run_state, write_json_atomic

FAKE_TRAINER = [sys.executable, str(Path(__file__).with_name("fake_trainer.py"))]


def _planned(out: Path, runs: int = 3) -> tuple[Preset, list[RunSpec]]:
    """`runs` 6-step runs (a checkpoint every 2) with their requests written."""
    base = get_preset("cpu")
    task = dataclasses.replace(base.tasks[0], demos=(2,), steps=6, save_freq=2, heldout=2)
    preset = dataclasses.replace(base, tasks=(task,), seeds=(0,))
    specs = plan_task(task, preset, num_episodes=8)[:runs]
    for spec in specs:
        write_json_atomic(spec.run_dir(out) / REQUEST_FILE, train_config(spec, task, out / "data", 0, out))
    return preset, specs


def test_a_resubmitted_study_skips_finished_runs_and_resumes_failed_ones_from_their_last_checkpoint(
    tmp_path, monkeypatch
):
    _, specs = _planned(tmp_path)
    calls = tmp_path / "calls.txt"
    monkeypatch.setenv("FAKE_TRAINER_CALLS", str(calls))
    monkeypatch.setenv("FAKE_TRAINER_FAIL_AT", "4")
    executor = SlurmExecutor(tmp_path, FAKE_TRAINER, SlurmOptions(cluster="debug"))
    outcome = executor.run(specs)
    assert outcome.failed == tuple(specs) and not outcome.done
    assert all(run_state(s, tmp_path) == ("resume", 4) for s in specs)
    assert all(json.loads((s.run_dir(tmp_path) / JOB_FILE).read_text())["cluster"] == "debug" for s in specs)

    monkeypatch.delenv("FAKE_TRAINER_FAIL_AT")
    (specs[0].run_dir(tmp_path) / DONE_FILE).write_text("{}")  # finished meanwhile: not submitted again
    outcome = executor.run(specs)
    assert outcome.done == (specs[0], specs[1], specs[2]) and not outcome.failed
    lines = calls.read_text().splitlines()
    assert len(lines) == 5 and all("resume=True from=4" in line for line in lines[3:])
    assert all(run_state(s, tmp_path).status == "done" for s in specs[1:])


def test_a_preempted_job_stops_lerobot_train_is_requeued_and_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    """The stand-in trainer signals its job as SLURM does on preemption (USR2) after its step-2 checkpoint;
    submitit's local executor requeues the job as SLURM would."""
    _, specs = _planned(tmp_path, runs=1)
    calls = tmp_path / "calls.txt"
    monkeypatch.setenv("FAKE_TRAINER_CALLS", str(calls))
    monkeypatch.setenv("FAKE_TRAINER_PREEMPT_AT", "2")
    outcome = SlurmExecutor(tmp_path, FAKE_TRAINER, SlurmOptions(cluster="local", timeout_min=10)).run(specs)
    assert outcome.done == (specs[0],), outcome
    assert calls.read_text().splitlines() == [f"pacdp {specs[0].name} resume=False from=0",
                                              f"pacdp {specs[0].name} resume=True from=2"]  # fmt: skip
    logs = "".join(p.read_text() for p in (tmp_path / "slurm").rglob("*.out"))
    assert "Caught signal SIGUSR2" in logs and "Calling checkpoint method" in logs and "Requeued job" in logs


@pytest.fixture
def study_dir(tmp_path) -> Path:
    """An output dir whose PushT dataset is 'converted' (206 demos): enough for planning."""
    info = tmp_path / "data" / "pusht" / "meta" / "info.json"
    info.parent.mkdir(parents=True)
    info.write_text(json.dumps({"total_episodes": 206}))
    return tmp_path


def test_dry_run_prints_the_arrays_sbatch_parameters_and_each_jobs_run_and_command(study_dir, capsys):
    argv = [f"--output_dir={study_dir}", "--executor=slurm", "--slurm.partition=gpu", "--slurm.account=proj",
            "--slurm.gpus_per_node=2", "--slurm.cpus_per_task=16", "--slurm.mem_gb=128", "--slurm.timeout_min=600",
            "--slurm.array_parallelism=4", "--dry_run=true", "--seeds=[0]", "--demos=[20]"]  # fmt: skip
    assert runner.main(argv) == 0
    out = capsys.readouterr().out
    sbatch = [line for line in out.splitlines() if line.startswith("#SBATCH")]
    for line in ("#SBATCH --partition=gpu", "#SBATCH --account=proj", "#SBATCH --gpus-per-node=2",
                 "#SBATCH --cpus-per-task=16", "#SBATCH --mem=128GB", "#SBATCH --time=600", "#SBATCH --nodes=1",
                 "#SBATCH --ntasks-per-node=1", "#SBATCH --array=0-2%3", "#SBATCH --signal=USR2@90"):  # fmt: skip
        assert line in sbatch, (line, sbatch)
    jobs = [line for line in out.splitlines() if line.startswith("job ")]
    assert jobs == [
        f"job {i}: pusht/d020_s0_{tag} (new) partition=gpu account=proj nodes=1 ntasks_per_node=1 gpus_per_node=2 "
        "cpus_per_task=16 mem=128GB time=600"
        for i, tag in enumerate(("dp", "bdp_rho-4.5", "pacdp_kl0.0001_rho-4.5"))
    ]
    commands = [line.strip() for line in out.splitlines() if line.startswith("  ") and "--config_path=" in line]
    assert len(commands) == 3 and all(c.split()[1:4] == ["launch", "--multi_gpu", "--num_processes=2"] for c in commands)
    assert commands[0].endswith(f"--config_path={study_dir / 'runs/pusht/main/d020_s0_dp/train_request.json'}")
    assert not (study_dir / "runs").exists() and not (study_dir / "slurm").exists()  # a dry run writes nothing


def test_a_run_whose_job_is_still_queued_is_not_submitted_again(study_dir, monkeypatch):
    preset = runner.resolve_preset(runner.StudyConfig(seeds=[0], demos=[20]))
    specs = plan_task(preset.tasks[0], preset, num_episodes=206)
    record = {"job_id": "812_1", "cluster": "slurm", "folder": str(study_dir / "slurm")}
    write_json_atomic(specs[1].run_dir(study_dir) / JOB_FILE, record)
    asked = []
    monkeypatch.setattr(slurm, "job_state", lambda r: asked.append(r) or "RUNNING")
    preview = SlurmExecutor(study_dir, FAKE_TRAINER, SlurmOptions()).preview(specs)
    assert preview.splitlines()[0] == "SLURM job array: 2 jobs (0 runs done, 1 still queued or running)"
    assert "#SBATCH --array=0-1%2" in preview and specs[1].name not in preview and asked == [record]
    monkeypatch.setattr(slurm, "job_state", lambda r: "TIMEOUT")  # ended: submitted again
    assert "SLURM job array: 3 jobs" in SlurmExecutor(study_dir, FAKE_TRAINER, SlurmOptions()).preview(specs)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--executor=gpu"], "--executor must be one of local, slurm, got 'gpu'."),
        (["--executor=slurm", "--slurm.cluster=mars"], "--slurm.cluster must be one of slurm, local, debug, got 'mars'."),
        (["--executor=slurm", "--slurm.cpus_per_task=0"], "--slurm.cpus_per_task must be >= 1, got 0."),
        (["--executor=slurm", "--max_chunk_steps=100"], "--max_chunk_steps is for --executor=local"),
    ],
)
def test_bad_executor_settings_are_one_line_and_exit_2_with_nothing_written(study_dir, capsys, flags, message):
    before = sorted(study_dir.rglob("*"))
    assert runner.main([f"--output_dir={study_dir}", *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-study: error: ") and message in err and len(err.splitlines()) == 1
    assert sorted(study_dir.rglob("*")) == before
