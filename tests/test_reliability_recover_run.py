"""pacdp-recover-run: a lerobot-train run killed while writing a checkpoint becomes resumable again.

The damaged checkpoints below hold what a kill leaves: LeRobot writes config.json, model.safetensors and
train_config.json first, then the processors, then training_state/, and moves `last` only at the end.
"""

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lerobot_pacdp.run_recovery import main
from lerobot_pacdp.train_runs import checkpoint_problem

from pacdp_testing import make_tiny_dataset

BIN = Path(sys.executable).parent
TINY_TRAINING = [
    "--policy.type=pacdp", "--policy.down_dims=[16,32]", "--policy.diffusion_step_embed_dim=16", "--policy.horizon=8",
    "--policy.n_action_steps=4", "--policy.drop_n_last_frames=3", "--policy.device=cpu", "--policy.push_to_hub=false",
    "--dataset.repo_id=local/tiny", "--wandb.enable=false", "--num_workers=0", "--batch_size=4", "--log_freq=2",
]  # fmt: skip


def lerobot_train(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    result = subprocess.run([str(BIN / "lerobot-train"), *args], capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def train_tiny_run(root: Path) -> Path:
    """A real 4-step lerobot-train run with checkpoints at steps 2 and 4."""
    make_tiny_dataset(root / "dataset", [12, 12, 12])
    out = root / "run"
    data = f"--dataset.root={root / 'dataset'}"
    lerobot_train(*TINY_TRAINING, data, "--steps=4", "--save_freq=2", f"--output_dir={out}")
    return out


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    return train_tiny_run(tmp_path_factory.mktemp("finished"))


@pytest.fixture
def run(finished_run, tmp_path) -> Path:
    return Path(shutil.copytree(finished_run, tmp_path / "run", symlinks=True))


def kill_during_write(step_dir: Path, seconds_ago: float = 3600) -> None:
    """Leave `step_dir` as a kill after model.safetensors and train_config.json leaves it, `seconds_ago`."""
    for path in step_dir.joinpath("pretrained_model").glob("policy_*"):
        path.unlink()
    shutil.rmtree(step_dir / "training_state")
    for path in (step_dir, *step_dir.rglob("*")):
        os.utime(path, (time.time() - seconds_ago,) * 2)


def recover(run: Path, capsys) -> tuple[int, str, str]:
    status = main([f"--output_dir={run}"])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_recover_points_last_at_the_newest_complete_checkpoint_and_moves_the_broken_one_aside(run, capsys):
    kill_during_write(run / "checkpoints" / "000004")
    (run / "checkpoints" / "last").unlink()
    (run / "checkpoints" / "last").symlink_to("000004")  # as if the kill hit a later save of the same step

    status, out, _ = recover(run, capsys)
    assert status == 0
    assert "Using checkpoint 000002 (step 2), the newest complete one" in out
    assert "Moved the incomplete checkpoint 000004" in out and "training_state/ is missing" in out
    config = run.absolute() / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    assert f"lerobot-train --config_path={config} --resume=true" in out
    assert os.readlink(run / "checkpoints" / "last") == "000002"
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["000002", "last"]
    moved = run / "incomplete_checkpoints" / "000004" / "pretrained_model"
    assert sorted(p.name for p in moved.iterdir()) == ["config.json", "model.safetensors", "train_config.json"]


def test_a_run_killed_during_its_first_checkpoint_has_nothing_to_resume_and_loses_nothing(run, capsys):
    shutil.rmtree(run / "checkpoints" / "000004")
    (run / "checkpoints" / "last").unlink()
    kill_during_write(run / "checkpoints" / "000002")
    before = sorted(p.relative_to(run) for p in run.rglob("*"))

    status, out, err = recover(run, capsys)
    assert status == 2 and out == ""
    assert err.strip() == (
        f"pacdp-recover-run: error: no complete checkpoint in {run}/checkpoints (000002: training_state/ is missing), "
        f"so there is nothing to resume: remove {run} (or pass another --output_dir) and start the run again."
    )
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before


def test_a_checkpoint_being_written_right_now_is_left_alone(run, capsys):
    kill_during_write(run / "checkpoints" / "000004", seconds_ago=5)
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    status, _, err = recover(run, capsys)
    assert status == 2 and re.search(r"000004 was written \d+ s ago: the run may still be saving it. Stop lerobot", err)
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before


def test_a_complete_run_is_left_as_it_is(run, capsys):
    status, out, _ = recover(run, capsys)
    assert status == 0 and "Using checkpoint 000004 (step 4): checkpoints/last already pointed to it." in out
    assert os.readlink(run / "checkpoints" / "last") == "000004" and not (run / "incomplete_checkpoints").exists()


def test_truncated_and_cut_off_files_make_a_checkpoint_incomplete(run):
    step_dir = run / "checkpoints" / "000004"
    assert checkpoint_problem(step_dir) is None
    weights = step_dir / "pretrained_model" / "model.safetensors"
    size = weights.stat().st_size
    os.truncate(weights, size - 100)
    (step_dir / "training_state" / "training_step.json").write_text('{"step": ')
    assert checkpoint_problem(step_dir) == (
        f"pretrained_model/model.safetensors is truncated ({size - 100} of {size} bytes); "
        "training_state/training_step.json is not valid JSON (cut off mid-write?)"
    )
    state_file = json.loads((step_dir / "pretrained_model" / "policy_preprocessor.json").read_text())["steps"][-1]
    (step_dir / "pretrained_model" / state_file["state_file"]).unlink()
    assert f"pretrained_model/{state_file['state_file']} is missing" in checkpoint_problem(step_dir)


@pytest.mark.parametrize(
    ("argv", "message"),
    [([], "pass --output_dir=DIR"), (["--output_dir={tmp}/nowhere"], "{tmp}/nowhere holds no checkpoints/ directory")],
)
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, capsys, argv, message):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pacdp-recover-run: error: ") and message.format(tmp=tmp_path) in err and "\n" not in err


def test_an_unknown_flag_is_refused_by_the_parser(tmp_path, capsys):
    with pytest.raises(SystemExit) as exited:
        main([f"--output_dir={tmp_path}", "--steps=3"])
    assert exited.value.code == 2 and "unrecognized arguments: --steps=3" in capsys.readouterr().err


@pytest.mark.slow
def test_the_readme_resume_command_works_after_recovering_a_killed_run(tmp_path, capsys):
    run = train_tiny_run(tmp_path)
    kill_during_write(run / "checkpoints" / "000004")
    (run / "checkpoints" / "last").unlink()
    (run / "checkpoints" / "last").symlink_to("000002")
    assert recover(run, capsys)[0] == 0

    lerobot_train(f"--config_path={run}/checkpoints/last/pretrained_model/train_config.json", "--resume=true")
    assert os.readlink(run / "checkpoints" / "last") == "000004"
    assert checkpoint_problem(run / "checkpoints" / "000004") is None
    step = json.loads((run / "checkpoints" / "000004" / "training_state" / "training_step.json").read_text())["step"]
    assert step == 4
