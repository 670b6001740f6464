"""Clear errors for an unsupported policy type, a missing checkpoint and a dataset that does not fit."""

import json
import shutil
from importlib.metadata import entry_points

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_pacdp.metrics import certificate, learned_prior, sweep
from lerobot_pacdp.metrics.checkpoints import (
    CheckpointNotFoundError,
    DatasetMismatchError,
    UnsupportedPolicyError,
    list_checkpoints,
    load_policy,
)
from lerobot_pacdp.metrics.data import EvaluationData


def _cli_fails(main, argv, capsys, *phrases):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for phrase in phrases:
        assert phrase in err, err


@pytest.fixture
def act_checkpoint(tiny_runs, tmp_path):
    """A checkpoint whose config.json names another LeRobot policy type."""
    path = shutil.copytree(tiny_runs["pacdp_s0"] / "checkpoints" / "000100" / "pretrained_model", tmp_path / "act")
    config = json.loads((path / "config.json").read_text())
    (path / "config.json").write_text(json.dumps(config | {"type": "act"}))
    return path


def test_unsupported_policy_type(act_checkpoint, capsys):
    with pytest.raises(UnsupportedPolicyError, match="'act' policy.*'pacdp' and 'diffusion'"):
        load_policy(act_checkpoint)
    _cli_fails(certificate.main, [f"--checkpoint={act_checkpoint}"], capsys, "pacdp-certify: error:", "'act' policy")
    _cli_fails(learned_prior.main, [f"--source={act_checkpoint}", "--output_dir=/tmp/unused"], capsys, "'act' policy")


def test_certificate_needs_a_pacdp_checkpoint(tiny_runs, capsys):
    dp = tiny_runs["dp_s0"] / "checkpoints" / "000100"
    _cli_fails(certificate.main, [f"--checkpoint={dp}"], capsys, "'diffusion' policy", "pacdp-learned-prior")


def test_missing_checkpoint(tmp_path, capsys):
    with pytest.raises(CheckpointNotFoundError, match="does not exist"):
        load_policy(tmp_path / "nope")
    with pytest.raises(CheckpointNotFoundError, match="holds no config.json and model.safetensors"):
        load_policy(tmp_path)
    with pytest.raises(CheckpointNotFoundError, match="neither a lerobot-train output directory"):
        list_checkpoints(tmp_path)
    _cli_fails(
        sweep.main,
        [f"--runs=[{tmp_path / 'nope'}]", f"--output_dir={tmp_path / 'out'}"],
        capsys,
        "pacdp-metrics: error:",
        "checkpoints",
    )
    _cli_fails(certificate.main, [f"--checkpoint={tmp_path / 'nope'}"], capsys, "does not exist")


def test_checkpoint_without_its_preprocessor(tiny_runs, tmp_path):
    path = shutil.copytree(tiny_runs["pacdp_s0"] / "checkpoints" / "000100" / "pretrained_model", tmp_path / "ckpt")
    for file in path.glob("policy_preprocessor*"):
        file.unlink()
    with pytest.raises(CheckpointNotFoundError, match="no saved preprocessor"):
        load_policy(path)


@pytest.fixture
def wrong_dataset(tmp_path):
    """Like the training data but with a 3-d observation.state."""
    features = {
        "observation.state": {"dtype": "float32", "shape": (3,), "names": None},
        "observation.environment_state": {"dtype": "float32", "shape": (16,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
    }
    dataset = LeRobotDataset.create("local/wrong", fps=10, features=features, root=tmp_path / "wrong", use_videos=False)
    for _ in range(12):
        dataset.add_frame({k: np.zeros(v["shape"], np.float32) for k, v in features.items()} | {"task": "t"})
    dataset.save_episode()
    dataset.finalize()
    return dataset


def test_dataset_that_does_not_match_the_policy(tiny_runs, tiny_dataset, wrong_dataset, tmp_path, capsys):
    loaded = load_policy(tiny_runs["pacdp_s0"] / "checkpoints" / "000100")
    with pytest.raises(DatasetMismatchError, match=r"'observation.state' has shape \(3,\), the policy expects \(2,\)"):
        EvaluationData(loaded.policy.config, "local/wrong", wrong_dataset.root, [0])
    with pytest.raises(DatasetMismatchError, match=r"has 6 episodes; episodes \[7\] do not exist"):
        EvaluationData(loaded.policy.config, "local/tiny", tiny_dataset.root, [0, 7])
    argv = [
        f"--runs=[{tiny_runs['pacdp_s0']}]",
        "--dataset.repo_id=local/wrong",
        f"--dataset.root={wrong_dataset.root}",
        "--episodes=0",
        f"--output_dir={tmp_path / 'out'}",
    ]
    _cli_fails(sweep.main, argv, capsys, "does not match the policy", "observation.state")


def test_console_scripts_are_these_mains():
    """The installed scripts run `sys.exit(main())`: the in-process exit-2 checks above cover them."""
    scripts = {ep.name: ep for ep in entry_points(group="console_scripts") if ep.name.startswith("pacdp-")}
    assert scripts["pacdp-metrics"].load() is sweep.main
    assert scripts["pacdp-certify"].load() is certificate.main
    assert scripts["pacdp-learned-prior"].load() is learned_prior.main


def test_a_truncated_checkpoint_is_one_line_and_leaves_no_output(tiny_runs, tmp_path, capsys):
    run = shutil.copytree(tiny_runs["frozen_s0"], tmp_path / "run", symlinks=True)
    weights = run / "checkpoints" / "000100" / "pretrained_model" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])  # a run killed while writing its first checkpoint
    out = tmp_path / "metrics"
    _cli_fails(sweep.main, [f"--runs=[{run}]", f"--output_dir={out}", "--nll=false"], capsys,
               "pacdp-metrics: error: cannot load the checkpoint", "000100", "truncated")  # fmt: skip
    assert not out.exists()
    cert = tmp_path / "cert.json"
    _cli_fails(certificate.main, [f"--checkpoint={weights.parent}", f"--output={cert}"], capsys, "truncated")
    assert not cert.exists()
