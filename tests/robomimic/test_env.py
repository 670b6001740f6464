"""The gymnasium environment on robosuite 1.5: seeding, observations, success, compat, vector envs."""

import logging

import gymnasium as gym
import h5py
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

import lerobot_pacdp  # noqa: F401
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.env import make_robosuite_env, seeded_reset_rngs
from lerobot_pacdp.robomimic.scripted_experts import LiftExpert, run_episode
from lerobot_pacdp.robomimic.tasks import TASKS


def _slice(task_name, key, generation=compat.NATIVE):
    start = 0
    for k, size in compat.object_layout(task_name, generation):
        if k == key:
            return slice(start, start + size)
        start += size
    raise KeyError(key)


# -- seeding ---------------------------------------------------------------------------------------------
def test_reset_is_deterministic_per_seed(lift_env):
    state = np.random.get_state()[1].copy()
    a, _ = lift_env.reset(seed=11)
    b, _ = lift_env.reset(seed=11)
    c, _ = lift_env.reset(seed=12)
    np.testing.assert_array_equal(a["environment_state"], b["environment_state"])
    np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
    assert not np.allclose(a["environment_state"][:3], c["environment_state"][:3])  # the cube moved
    # Unseeded resets continue the seeded sequence deterministically.
    lift_env.reset(seed=11)
    d1, _ = lift_env.reset()
    lift_env.reset(seed=11)
    d2, _ = lift_env.reset()
    np.testing.assert_array_equal(d1["environment_state"], d2["environment_state"])
    np.testing.assert_array_equal(np.random.get_state()[1], state)  # numpy's global generator untouched


def test_seeding_sets_every_robosuite_generator(lift_env):
    env = lift_env.robosuite_env
    with seeded_reset_rngs(env, 5):
        first = np.random.uniform()
    with seeded_reset_rngs(env, 5):
        assert np.random.uniform() == first
    assert isinstance(env.rng, np.random.Generator)


# -- observations ----------------------------------------------------------------------------------------
def test_observations_have_the_declared_spaces_and_robosuite_object_state(lift_env):
    obs, info = lift_env.reset(seed=0)
    assert lift_env.observation_space.contains(obs)
    assert obs["agent_pos"].shape == (9,) and obs["environment_state"].shape == (10,)
    raw = lift_env.robosuite_env._get_observations(force_update=True)
    np.testing.assert_allclose(obs["environment_state"], raw["object-state"])
    np.testing.assert_allclose(obs["agent_pos"][:3], raw["robot0_eef_pos"])
    assert info == {"is_success": False}
    assert lift_env.task == "lift" and lift_env.task_description == TASKS["lift"].description


def test_observation_layout_equals_the_converted_dataset_for_the_same_state(lift_env, scripted_lift, scripted_lift_dataset):
    path, _, _ = scripted_lift
    dataset = LeRobotDataset("local/robomimic_lift", root=scripted_lift_dataset)
    with h5py.File(path, "r") as f:
        states = f["data/demo_1/states"][()]
    offset = int(dataset.meta.episodes["dataset_from_index"][1])
    for t in (0, len(states) // 2, len(states) - 1):
        obs, _ = lift_env.reset(seed=0, options={"state": states[t]})
        frame = dataset[offset + t]
        np.testing.assert_allclose(obs["agent_pos"], frame["observation.state"].numpy(), atol=1e-5)
        np.testing.assert_allclose(obs["environment_state"], frame["observation.environment_state"].numpy(), atol=1e-5)


# -- success, termination, truncation --------------------------------------------------------------------
def test_expert_episode_reports_success_and_terminates(lift_env):
    expert = LiftExpert(lift_env.robosuite_env)
    success, demo = run_episode(lift_env, expert, seed=3)
    assert success and demo is not None and demo.rewards[-1] == 1.0
    # The success step terminated the episode: it is the demo's last step, with is_success in info.
    assert bool(lift_env.robosuite_env._check_success())
    _, reward, terminated, truncated, info = lift_env.step(np.zeros(7))
    assert terminated and not truncated and info["is_success"] and reward == 1.0


def test_budget_truncates_and_actions_are_validated():
    env = gym.make("pacdp_robomimic/lift-v0", episode_length=3, render_mode=None, disable_env_checker=True)
    try:
        env.reset(seed=0)
        results = [env.step(np.zeros(7, dtype=np.float32)) for _ in range(3)]
        assert [r[3] for r in results] == [False, False, True] and not any(r[2] for r in results)
        assert not results[-1][4]["is_success"]
        with pytest.raises(ValueError, match="7-d actions"):
            env.unwrapped.step(np.zeros(14))
    finally:
        env.close()


def test_render_gives_a_frame_or_skips_cleanly(lift_env, caplog):
    lift_env.reset(seed=0)
    with caplog.at_level(logging.WARNING, logger="lerobot_pacdp.robomimic.env"):
        frames = [lift_env.render() for _ in range(2)]
    for frame in frames:
        assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    if lift_env._render_unavailable is None:  # an offscreen OpenGL context exists (MUJOCO_GL=egl/osmesa)
        assert frames[0].any(), "a real render is not all black"
    else:  # no renderer: black frames and one warning saying how to get videos
        assert not frames[0].any()
        warnings = [r.getMessage() for r in caplog.records if "offscreen rendering is unavailable" in r.getMessage()]
        assert len(warnings) == 1 and "MUJOCO_GL=egl" in warnings[0]


# -- robosuite <= 1.4 compatibility: each difference -----------------------------------------------------
def test_compat_lift_relative_position_sign(lift_env, lift_env_legacy):
    """Difference 1: gripper_to_cube_pos is eef - cube in <= 1.4, cube - eef in 1.5."""
    native, _ = lift_env.reset(seed=4)
    legacy, _ = lift_env_legacy.reset(seed=4)
    rel = _slice("lift", "gripper_to_cube_pos")
    eef, cube = native["agent_pos"][:3], native["environment_state"][:3]
    np.testing.assert_allclose(native["environment_state"][rel], cube - eef, atol=1e-9)
    eef, cube = legacy["agent_pos"][:3], legacy["environment_state"][:3]
    np.testing.assert_allclose(legacy["environment_state"][rel], eef - cube, atol=1e-9)


def test_compat_per_object_order(square_env, square_env_legacy):
    """Difference 2: [pos, quat, to_eef_pos, to_eef_quat] in <= 1.4 vs [to_eef_pos, to_eef_quat, pos, quat]."""
    native, _ = square_env.reset(seed=2)
    legacy, _ = square_env_legacy.reset(seed=2)
    raw = square_env_legacy.last_raw_obs
    for key in ("SquareNut_pos", "SquareNut_quat", "SquareNut_to_robot0_eef_pos", "SquareNut_to_robot0_eef_quat"):
        np.testing.assert_allclose(legacy["environment_state"][_slice("square", key, "1.4")], raw[key])
        np.testing.assert_allclose(native["environment_state"][_slice("square", key)], square_env.last_raw_obs[key])
    np.testing.assert_allclose(legacy["environment_state"][:3], raw["SquareNut_pos"])
    np.testing.assert_allclose(native["environment_state"][7:10], raw["SquareNut_pos"])


def test_compat_reset_observation_has_no_zeroed_relative_fields(square_env):
    """Difference 4: robosuite 1.5's reset() zeroes *_to_robot0_eef_*; the env forces an update."""
    raw_env = square_env.robosuite_env
    with seeded_reset_rngs(raw_env, 9):
        raw_reset = raw_env.reset()
    assert not raw_reset["SquareNut_to_robot0_eef_pos"].any()  # the robosuite 1.5 quirk itself
    obs, _ = square_env.reset(seed=9)
    rel = obs["environment_state"][_slice("square", "SquareNut_to_robot0_eef_pos")]
    assert np.abs(rel).min() > 0
    np.testing.assert_allclose(rel, raw_env._get_observations(force_update=True)["SquareNut_to_robot0_eef_pos"])


def test_set_state_observes_the_restored_state_not_the_one_before(square_env):
    """Difference 4 after a restore: the nut's position in the gripper frame, R_eef^T (p_nut - p_eef)."""
    from robosuite.utils.transform_utils import quat2mat

    square_env.reset(seed=4)
    restored = square_env.get_state()
    for _ in range(10):  # move the arm away, so the previous pass's poses differ from the restored ones
        square_env.step(np.array([0.8, 0.8, 0.8, 0.0, 0.0, 0.0, -1.0]))
    raw = square_env.set_state(restored)
    oracle = quat2mat(raw["robot0_eef_quat"]).T @ (raw["SquareNut_pos"] - raw["robot0_eef_pos"])
    np.testing.assert_allclose(raw["SquareNut_to_robot0_eef_pos"], oracle, atol=1e-6)


def test_compat_physics_and_controller_frame(lift_env, lift_env_legacy):
    assert lift_env_legacy.robosuite_env.lite_physics is False
    for env, frame in ((lift_env, "base"), (lift_env_legacy, "world")):
        controller = env.robosuite_env.robots[0].composite_controller.part_controllers["right"]
        assert controller.input_ref_frame == frame


@pytest.fixture(scope="module")
def transport_envs():
    envs = {g: make_robosuite_env("transport", g) for g in compat.GENERATIONS}
    yield envs
    for env in envs.values():
        env.close()


def test_compat_transport_flags_and_world_frame_deltas(transport_envs):
    """Difference 3: the flags move to the end, and deltas are world-frame for both (rotated) arms."""
    from lerobot_pacdp.robomimic.env import observation_vectors, robosuite_reset

    task = TASKS["transport"]
    moved = {}
    for generation, env in transport_envs.items():
        for i in (0, 1):
            assert env.robots[i].composite_controller.part_controllers["right"].input_ref_frame == compat.controller_input_ref_frame(generation)
        raw = robosuite_reset(env, 1)
        _, obj = observation_vectors(task, raw, generation)
        flags = np.array([raw["payload_in_target_bin"], raw["trash_in_trash_bin"]], dtype=float).reshape(-1)
        if generation == compat.LEGACY:
            np.testing.assert_array_equal(obj[-2:], flags)
            np.testing.assert_allclose(obj[-14:-11], raw["gripper0_to_payload"])
            assert _slice("transport", "gripper0_to_payload", generation) == slice(27, 30)
        else:
            np.testing.assert_array_equal(obj[27:29], flags)  # just after trash_bin_pos
            assert _slice("transport", "trash_bin_pos").stop == 27
        # Push robot1's hand along +x (world); measure where it goes.
        start = np.array(raw["robot1_eef_pos"])
        action = np.zeros(14)
        action[7] = 1.0
        for _ in range(5):
            raw, *_ = env.step(action)
        moved[generation] = np.array(raw["robot1_eef_pos"]) - start
    legacy = moved[compat.LEGACY]
    assert legacy[0] > 0.03 and abs(legacy[0]) > 3 * max(abs(legacy[1]), abs(legacy[2]))  # world +x
    assert abs(moved[compat.NATIVE][0]) < 0.5 * abs(moved[compat.NATIVE][1])  # base frame: rotated 90 deg


# -- LeRobot vector envs ---------------------------------------------------------------------------------
def _check_vector_env(envs, n):
    from lerobot.envs.utils import preprocess_observation

    vec = envs["robomimic"][0]
    obs, _ = vec.reset(seed=list(range(n)))
    batch = preprocess_observation(obs)
    assert batch["observation.state"].shape == (n, 9) and batch["observation.environment_state"].shape == (n, 10)
    assert vec.call("_max_episode_steps")[0] == 400
    _, reward, terminated, truncated, info = vec.step(np.zeros((n, 7), dtype=np.float32))
    assert reward.shape == (n,) and list(info["is_success"]) == [False] * n
    again, _ = vec.reset(seed=list(range(n)))
    np.testing.assert_array_equal(again["environment_state"], obs["environment_state"])
    assert not np.allclose(obs["environment_state"][0], obs["environment_state"][1])
    frames = vec.call("render")
    assert np.stack(frames).shape == (n, 256, 256, 3)


@pytest.mark.parametrize(
    "use_async, vector_class", [(False, "SyncVectorEnv"), pytest.param(True, "AsyncVectorEnv", marks=pytest.mark.slow)]
)
def test_vector_envs_via_lerobot_make_env(use_async, vector_class):
    from lerobot.envs.factory import make_env, make_env_config
    from lerobot.envs.utils import close_envs

    envs = make_env(make_env_config("robomimic", task="lift"), n_envs=2, use_async_envs=use_async)
    try:
        assert type(envs["robomimic"][0]).__name__ == vector_class
        _check_vector_env(envs, 2)
    finally:
        close_envs(envs)


@pytest.mark.parametrize("name", ["can", "tool_hang"])
def test_task_layout_matches_robosuite_object_state(name, transport_envs):
    """The table's layout is robosuite 1.5's object-state for every task (Lift/Square/Transport above)."""
    from lerobot_pacdp.robomimic.env import observation_vectors, robosuite_reset

    task = TASKS[name]
    env = make_robosuite_env(name)
    try:
        raw = robosuite_reset(env, 0)
        state, obj = observation_vectors(task, raw)
        np.testing.assert_array_equal(obj, raw["object-state"])
        assert state.shape == (task.state_dim,) and obj.shape == (task.object_dim,)
        assert env.action_dim == task.action_dim
    finally:
        env.close()
    raw = robosuite_reset(transport_envs[compat.NATIVE], 0)
    np.testing.assert_array_equal(observation_vectors(TASKS["transport"], raw)[1], raw["object-state"])


@pytest.mark.slow
@pytest.mark.skipif(
    __import__("ctypes.util").util.find_library("OSMesa") is None, reason="no libOSMesa for offscreen rendering"
)
def test_render_with_an_offscreen_renderer(tmp_path):
    """On a CPU machine with libOSMesa the env renders real agentview frames, also after hard resets."""
    import os
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from lerobot_pacdp.robomimic.env import RobomimicEnv\n"
        "env = RobomimicEnv('lift', render_height=96, render_width=128)\n"
        "env.reset(seed=0); a = env.render(); env.step(np.zeros(7)); b = env.render()\n"
        "env.reset(seed=1); c = env.render()\n"
        "assert env._render_unavailable is None, env._render_unavailable\n"
        "assert a.shape == (96, 128, 3) and a.dtype == np.uint8 and a.std() > 10\n"
        "assert not np.array_equal(a, c)  # the cube moved\n"
        "env.close()\n"
    )
    # With no MUJOCO_GL set, the env picks OSMesa itself (robosuite alone would force EGL and fail).
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
