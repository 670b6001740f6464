"""Scripted experts and the robomimic-format files they write."""

import json
import os
import platform
import subprocess
import sys

import h5py
import numpy as np
import pytest

from lerobot_pacdp.robomimic import scripted_experts
from lerobot_pacdp.robomimic.hdf5_adapter import inspect_hdf5
from lerobot_pacdp.robomimic.scripted_experts import collect_demos, measure_success_rate


def test_written_file_has_the_released_files_schema(scripted_lift):
    path, demos, stats = scripted_lift
    assert stats.successes == len(demos) == 4
    with h5py.File(path, "r") as f:
        data = f["data"]
        assert data.attrs["total"] == sum(len(d) for d in demos)
        env_args = json.loads(data.attrs["env_args"])
        assert env_args["env_name"] == "Lift" and env_args["env_version"].startswith("1.5")
        assert env_args["env_kwargs"]["control_freq"] == 20 and env_args["env_kwargs"]["robots"] == ["Panda"]
        assert env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]["type"] == "OSC_POSE"
        for i, demo in enumerate(demos):
            group = data[f"demo_{i}"]
            n = group.attrs["num_samples"]
            assert n == len(demo) and group.attrs["model_file"].startswith("<mujoco")
            assert group["actions"].shape == (n, 7) and group["states"].shape[0] == n
            assert group["rewards"].shape == (n,) and group["dones"].shape == (n,)
            assert group["rewards"][-1] == 1.0 and group["dones"][-1] == 1 and not group["rewards"][:-1].any()
            assert np.abs(group["actions"][()]).max() <= 1.0
            for key in ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos"):
                assert group[f"obs/{key}"].shape[0] == n and key in group["next_obs"]
            np.testing.assert_array_equal(group["next_obs/object"][:-1], group["obs/object"][1:])
        train = [n.decode() for n in f["mask/train"][()]]
        valid = [n.decode() for n in f["mask/valid"][()]]
        assert sorted(train + valid) == [f"demo_{i}" for i in range(4)] and len(valid) == 1
    info = inspect_hdf5(path)  # and the converter accepts it
    assert info.task.name == "lift" and info.generation == "1.5"


def test_lift_demos_are_short_and_deterministic_per_seed(scripted_lift):
    _, demos, _ = scripted_lift
    assert all(20 <= len(d) <= 80 for d in demos)
    again, _, _ = collect_demos("lift", 1, seed=7, action_noise=0.05)
    np.testing.assert_array_equal(again[0].actions, demos[0].actions)
    np.testing.assert_array_equal(again[0].states, demos[0].states)


def test_action_noise_diversifies_the_demos(scripted_lift):
    _, noisy, _ = scripted_lift
    clean, _, _ = collect_demos("lift", 1, seed=7, action_noise=0.0)
    # Same initial state (same seed), different actions.
    np.testing.assert_array_equal(clean[0].states[0], noisy[0].states[0])
    n = min(len(clean[0]), len(noisy[0]))
    assert not np.allclose(clean[0].actions[:n, :6], noisy[0].actions[:n, :6])


@pytest.mark.parametrize(("task", "episodes"), [("can", 2), ("square", 2)])
def test_can_and_square_experts_succeed(task, episodes):
    stats = measure_success_rate(task, episodes, seed=0)
    assert stats.successes == episodes, stats.as_dict()
    assert all(length < 400 for length in stats.success_lengths)


def test_recorded_can_observations_are_what_the_environment_observes():
    """Frame 0 equals the reset observation and every frame the one seen on restoring its state (the
    relative fields once held the previous state's can: frame 0 pointed at where the last episode left it)."""
    from lerobot_pacdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv("can", render_mode=None)
    try:
        expert = scripted_experts.CanExpert(env.robosuite_env, np.random.default_rng(0))
        success, demo = scripted_experts.run_episode(env, expert, seed=3)
        assert success
        reset_obs, _ = env.reset(seed=3)
        np.testing.assert_allclose(demo.obs["object"][0], reset_obs["environment_state"], atol=1e-9)
        for t in (len(demo) // 2, len(demo) - 1):  # the can moves with the gripper in the second half
            restored = env.set_state(demo.states[t])
            np.testing.assert_allclose(demo.obs["object"][t][:3], restored["Can_to_robot0_eef_pos"], atol=1e-9)
    finally:
        env.close()


def test_cli_writes_a_file_and_reports_the_success_rate(tmp_path, capfd):  # capfd: a child process may record
    out = tmp_path / "demos.hdf5"
    argv = ["--task=lift", "--num_demos=2", f"--output={out}", "--seed=1", "--action_noise=0.02"]
    assert scripted_experts.main(argv) == 0
    assert "lift: 2/2 successful episodes (100%)" in capfd.readouterr().out
    with h5py.File(out, "r") as f:
        assert sorted(f["data"].keys()) == ["demo_0", "demo_1"]
        assert json.loads(f["data"].attrs["scripted_expert"])["action_noise"] == 0.02
    assert scripted_experts.main(argv) == 2  # exists, no --overwrite
    assert "already exists" in capfd.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--task=transport", "--num_demos=1"], "no scripted expert for 'transport'"),
        (["--task=stack", "--num_demos=1"], "unknown robomimic task"),
        (["--task=lift", "--num_demos=0"], "--num_demos must be >= 1"),
        (["--task=lift", "--num_demos=1", "--action_noise=-1"], "--action_noise must be >= 0"),
        (["--task=lift"], "pass --task=<lift|can|square> --num_demos=N --output=FILE.hdf5."),
        (["--task=lift", "--num_demos=1", "--valid_fraction=1"], "--valid_fraction must be in [0, 1), got 1.0."),
    ],
)
def test_cli_bad_input_exits_2(tmp_path, capsys, argv, message):
    assert scripted_experts.main([*argv, f"--output={tmp_path / 'x.hdf5'}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-scripted-demos: error:") and message in err and "Traceback" not in err
    assert not (tmp_path / "x.hdf5").exists()


def test_recording_is_pinned_to_openblas_haswell_kernels_where_the_cpu_runs_them(monkeypatch):
    from numpy._core._multiarray_umath import __cpu_features__ as cpu

    monkeypatch.setitem(cpu, "AVX2", True)
    monkeypatch.setitem(cpu, "FMA3", True)
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Sandybridge")
    env = scripted_experts.blas_pinned_environment()
    assert env is not None and env["OPENBLAS_CORETYPE"] == "Haswell" and env["PATH"] == os.environ["PATH"]
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    assert scripted_experts.blas_pinned_environment() is None  # already pinned: record in this process
    monkeypatch.delenv("OPENBLAS_CORETYPE")
    monkeypatch.setitem(cpu, "AVX2", False)
    assert scripted_experts.blas_pinned_environment() is None  # a CPU without AVX2 cannot run Haswell's kernels
    monkeypatch.setitem(cpu, "AVX2", True)
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert scripted_experts.blas_pinned_environment() is None  # no x86 kernels to pin


def _demo_arrays(path) -> dict[str, np.ndarray]:
    with h5py.File(path) as f:
        return {k: f["data/demo_0"][k][()] for k in ("actions", "states")}


def _record(out, coretype: str, code: str) -> None:
    env = {**os.environ, "OPENBLAS_CORETYPE": coretype, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", code, "--task=can", "--num_demos=1", f"--output={out}",
                    "--action_noise=0.05"], env=env, check=True, capture_output=True)  # fmt: skip


_RUNS_HASWELL_KERNELS = (os.environ.get("OPENBLAS_CORETYPE") == "Haswell"
                         or scripted_experts.blas_pinned_environment() is not None)


@pytest.mark.skipif(not _RUNS_HASWELL_KERNELS, reason="OpenBLAS's Haswell kernels need an x86-64 CPU with AVX2 and FMA")
def test_the_command_records_the_same_can_demo_whatever_openblas_kernels_the_machine_picks(tmp_path):
    command = "import sys; from lerobot_pacdp.robomimic.scripted_experts import main; sys.exit(main())"
    unpinned = ("import sys; from lerobot_pacdp.robomimic import scripted_experts as s; "
                "s.blas_pinned_environment = lambda: None; sys.exit(s.main())")  # fmt: skip
    for name, coretype, code in [("haswell", "Haswell", command), ("sandybridge", "Sandybridge", command),
                                 ("sandybridge_unpinned", "Sandybridge", unpinned)]:  # fmt: skip
        _record(tmp_path / f"{name}.hdf5", coretype, code)
    haswell, sandybridge = _demo_arrays(tmp_path / "haswell.hdf5"), _demo_arrays(tmp_path / "sandybridge.hdf5")
    unpinned_demo = _demo_arrays(tmp_path / "sandybridge_unpinned.hdf5")
    # Sandybridge's kernels, left to run, record another demo; the command records Haswell's demo under them.
    assert not np.array_equal(unpinned_demo["states"], haswell["states"])
    for key in ("actions", "states"):
        np.testing.assert_array_equal(sandybridge[key], haswell[key])
