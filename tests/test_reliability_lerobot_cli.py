"""What users of lerobot-train and lerobot-eval see for a bad `--policy.*` / `--env.*` value or a checkpoint
that does not fit the env: this package's one-line message, never draccus' generic one or a traceback,
and nothing written."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.modeling_pacdp import PacdpPolicy
from lerobot_pacdp.robomimic.checkpoint_fit import check_checkpoint_fits_env

from pacdp_testing import tiny_config

BAD_POLICY_FLAGS = [  # (flag, the field and the value the message must name)
    ("--policy.kl_weight=-1", "kl_weight", "-1.0"),
    ("--policy.delta=1.5", "delta", "1.5"),
    ("--policy.prior_rho=nan", "prior_rho", "nan"),
    ("--policy.inference_mode=foo", "inference_mode", "'foo'"),
    ("--policy.num_train_samples=0", "num_train_samples", "0"),
    ("--policy.compile_model=true", "compile_model", "True"),
]


def run_lerobot(script: str, argv: list[str], monkeypatch, capsys) -> tuple[int, str]:
    """Run lerobot-train or lerobot-eval's `main` in this process; (exit status, stderr)."""
    import importlib

    module = importlib.import_module(f"lerobot.scripts.lerobot_{script}")
    monkeypatch.setattr(sys, "argv", [f"lerobot-{script}", *argv])
    with pytest.raises(SystemExit) as stopped:
        module.main()
    return stopped.value.code, capsys.readouterr().err


def the_error_line(err: str) -> str:
    """The one `error: ...` line; no draccus wrapper, no traceback of the error (LeRobot's unrelated
    torchcodec notice at import may precede it)."""
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err[-3000:]
    assert "Couldn't instantiate" not in err and "Could not decode" not in err and "draccus" not in err, err[-3000:]
    return lines[0]


@pytest.mark.parametrize(("flag", "field", "value"), BAD_POLICY_FLAGS)
def test_lerobot_train_names_the_bad_policy_field_and_its_value(tmp_path, monkeypatch, capsys, flag, field, value):
    out = tmp_path / "out"
    status, err = run_lerobot(
        "train", ["--policy.type=pacdp", flag, "--dataset.repo_id=local/x", f"--output_dir={out}"], monkeypatch, capsys
    )
    line = the_error_line(err)
    assert status == 1 and line.startswith("error: `policy`: ") and field in line and value in line
    assert not out.exists()


def test_lerobot_train_names_a_bad_field_of_a_config_file(tmp_path, monkeypatch, capsys):
    config = tmp_path / "train.json"
    config.write_text(json.dumps({"dataset": {"repo_id": "local/x"}, "policy": {"type": "pacdp", "delta": 2.0}}))
    argv = [f"--config_path={config}", f"--output_dir={tmp_path / 'out'}"]
    status, err = run_lerobot("train", argv, monkeypatch, capsys)
    assert status == 1 and "`delta` must lie strictly between 0 and 1, got 2.0" in the_error_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train.json"]


def test_the_installed_lerobot_train_command_names_the_field_too(tmp_path):
    """Through the real entry point: LeRobot's plugin discovery is what installs the one-line errors."""
    result = subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-train"), "--policy.type=pacdp", "--policy.kl_weight=-1",
         "--dataset.repo_id=local/x", f"--output_dir={tmp_path / 'out'}"],
        capture_output=True, text=True, timeout=300, env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    assert result.returncode == 1
    assert "`kl_weight` (lambda) must be a finite number >= 0, got -1.0" in the_error_line(result.stderr)
    assert not (tmp_path / "out").exists()


def save_checkpoint(path: Path, state: int, env: int, action: int, dataset_meta: dict | None = None) -> Path:
    """A tiny PAC-DP checkpoint taking `observation.state` (state,), `observation.environment_state` (env,),
    giving `action` (action,); with `dataset_meta`, its train_config.json names a dataset holding that
    meta/robomimic.json."""
    config = tiny_config()
    config.input_features = {
        "observation.state": PolicyFeature(FeatureType.STATE, (state,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (env,)),
    }
    config.output_features = {"action": PolicyFeature(FeatureType.ACTION, (action,))}
    PacdpPolicy(config).save_pretrained(path)
    sizes = {"observation.state": state, "observation.environment_state": env, "action": action}
    stats = {key: {"min": torch.zeros(n), "max": torch.ones(n)} for key, n in sizes.items()}
    for processor in make_pre_post_processors(config, dataset_stats=stats):
        processor.save_pretrained(path)
    if dataset_meta is not None:
        dataset = path.parent / "dataset"
        (dataset / "meta").mkdir(parents=True)
        (dataset / "meta" / "robomimic.json").write_text(json.dumps(dataset_meta))
        (path / "train_config.json").write_text(json.dumps({"dataset": {"repo_id": "local/d", "root": str(dataset)}}))
    return path


@pytest.fixture
def lift_checkpoint(tmp_path) -> Path:
    """Trained on converted Lift demos: state 9, environment_state 10, action 7."""
    meta = {"format": "lerobot_pacdp.robomimic/1", "task": "lift", "robosuite_compat": "1.5"}
    return save_checkpoint(tmp_path / "lift_checkpoint", 9, 10, 7, meta)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--policy.kl_weight=-1"], "error: `kl_weight` (lambda) must be a finite number >= 0, got -1.0."),
        (["--env.task=unknown"], "--env.task='unknown' is not a robomimic task; choose one of lift, can, square"),
        (["--env.robosuite_compat=2.0"], "--env.robosuite_compat must be '1.5' (native robosuite 1.5 layout) or '1.4'"),
        (["--env.episode_length=0"], "--env.episode_length must be >= 1, got 0."),
    ],
)
def test_lerobot_eval_names_bad_policy_and_env_flags(tmp_path, lift_checkpoint, monkeypatch, capsys, flags, message):
    out = tmp_path / "eval"
    argv = [f"--policy.path={lift_checkpoint}", "--env.type=robomimic", *flags, f"--output_dir={out}"]
    status, err = run_lerobot("eval", argv, monkeypatch, capsys)
    assert status == 1 and message in the_error_line(err)
    assert not out.exists()


def test_lerobot_eval_refuses_a_lift_checkpoint_in_can_before_building_the_env(
    tmp_path, lift_checkpoint, monkeypatch, capsys
):
    from lerobot_pacdp.robomimic.env import RobomimicEnv

    def no_env(*args, **kwargs):
        raise AssertionError("the env was built before the mismatch was found")

    monkeypatch.setattr(RobomimicEnv, "__init__", no_env)
    out = tmp_path / "eval"
    argv = [f"--policy.path={lift_checkpoint}", "--env.type=robomimic", "--env.task=can", f"--output_dir={out}"]
    status, err = run_lerobot("eval", argv, monkeypatch, capsys)
    line = the_error_line(err)
    assert status == 1
    assert "observation.environment_state has shape [10] in the checkpoint but [14] in can" in line
    assert "It was trained on lift (meta/robomimic.json of its dataset); evaluate it with --env.task=lift." in line
    assert not out.exists()  # no output dir, no empty videos/


def test_without_its_dataset_the_task_is_inferred_from_the_checkpoints_shapes(tmp_path):
    checkpoint = save_checkpoint(tmp_path / "ck", 9, 14, 7)  # Can or Square shapes, no train_config.json
    lift_shapes = {"observation.state": (9,), "observation.environment_state": (10,), "action": (7,)}
    with pytest.raises(ValueError, match=r"trained on can or square \(by its feature shapes\); evaluate it in"):
        check_checkpoint_fits_env(checkpoint, lift_shapes, "lift", "1.5", compat_given=False)
    pusht = save_checkpoint(tmp_path / "pusht", 2, 16, 2)
    with pytest.raises(ValueError, match=r"state has shape \[2\] in the checkpoint but \[9\].*on another dataset"):
        check_checkpoint_fits_env(pusht, lift_shapes, "lift", "1.5", compat_given=False)


def test_a_checkpoint_trained_on_robosuite_14_data_needs_the_14_conventions_unless_told_otherwise(tmp_path):
    meta = {"format": "lerobot_pacdp.robomimic/1", "task": "square", "robosuite_compat": "1.4"}
    checkpoint = save_checkpoint(tmp_path / "ck", 9, 14, 7, meta)
    shapes = {"observation.state": (9,), "observation.environment_state": (14,), "action": (7,)}
    with pytest.raises(ValueError, match=r"recorded with robosuite 1.4 conventions.*pass --env.robosuite_compat=1.4"):
        check_checkpoint_fits_env(checkpoint, shapes, "square", "1.5", compat_given=False)
    check_checkpoint_fits_env(checkpoint, shapes, "square", "1.4", compat_given=False)
    check_checkpoint_fits_env(checkpoint, shapes, "square", "1.5", compat_given=True)


def test_lerobot_eval_refuses_a_checkpoint_without_its_processor_files(tmp_path, lift_checkpoint, monkeypatch, capsys):
    (lift_checkpoint / "policy_preprocessor.json").unlink()
    out = tmp_path / "eval"
    argv = [f"--policy.path={lift_checkpoint}", "--env.type=robomimic", "--env.task=lift", f"--output_dir={out}"]
    status, err = run_lerobot("eval", argv, monkeypatch, capsys)
    line = the_error_line(err)
    assert status == 1 and "lacks policy_preprocessor.json, the processors (with the normalisation stats)" in line
    assert not out.exists()
