"""The PushT zarr -> LeRobotDataset converter: geometry against gym_pusht, output contents, errors, CLI."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import zarr
from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from lerobot_pacdp.datasets import pusht_zarr
from lerobot_pacdp.datasets.pusht_geometry import (
    GOAL_POSE,
    SUCCESS_THRESHOLD,
    keypoints_and_coverage,
    reward_and_success,
)
from lerobot_pacdp.datasets.pusht_zarr import (
    TASK,
    PushTConversionError,
    convert_pusht_zarr,
    main,
)
from lerobot_pacdp.episodes import EpisodeSelectionError, parse_episodes

from pacdp_testing import PUSHT_ZARR

# agent x, y, block x, y, angle; the agent is kept clear of the block so the reset's physics step cannot push it.
ENV_STATES = [
    [50.0, 50.0, 256.0, 256.0, np.pi / 4],
    [450.0, 450.0, 200.0, 300.0, 3.0],
    [60.0, 450.0, 300.0, 150.0, -1.2],
    [450.0, 60.0, 222.99, 381.6, 0.0],
    [60.0, 60.0, 330.0, 330.0, 5.5],
]
FAR_POSE = [80.0, 420.0, 0.3]  # a block pose with no overlap with the goal T


@pytest.fixture(scope="module")
def pusht_env():
    import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)

    env = gym.make("gym_pusht/PushT-v0", obs_type="environment_state_agent_pos")
    yield env
    env.close()


@pytest.mark.parametrize("state", ENV_STATES)
def test_keypoints_and_coverage_match_gym_pusht(pusht_env, state):
    observation, info = pusht_env.reset(options={"reset_to_state": np.array(state)})
    # reset_to_state sets the block position before its angle, which rotates the body about its centre of
    # gravity and moves the origin, so compare at the pose the env actually ended up in.
    pose = info["block_pose"]
    keypoints, coverage = keypoints_and_coverage(pose[None])
    np.testing.assert_allclose(keypoints[0], observation["environment_state"], atol=1e-4)
    np.testing.assert_allclose(observation["agent_pos"], state[:2], atol=1e-4)
    assert coverage[0] == pytest.approx(pusht_env.unwrapped._get_coverage(), abs=1e-9)


def test_goal_pose_and_threshold_match_gym_pusht(pusht_env):
    pusht_env.reset(seed=0)
    np.testing.assert_allclose(pusht_env.unwrapped.goal_pose, GOAL_POSE)
    assert pusht_env.unwrapped.success_threshold == SUCCESS_THRESHOLD


def test_block_on_the_goal_is_a_success_and_far_away_is_not():
    nudged = GOAL_POSE + [6.0, 0.0, 0.0]
    _, coverage = keypoints_and_coverage(np.stack([GOAL_POSE, np.array(FAR_POSE), nudged]))
    reward, success = reward_and_success(coverage)
    assert coverage[0] == pytest.approx(1.0)
    assert coverage[1] == 0.0
    np.testing.assert_allclose(reward[:2], [1.0, 0.0])
    assert 0.0 < reward[2] < 1.0
    assert success.tolist() == [True, False, False]


def write_replay_buffer(path: Path, state: np.ndarray, action: np.ndarray, episode_ends: list[int]) -> Path:
    """A Diffusion-Policy-style replay buffer (zarr v2, like the real one: every chunk file written)."""
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    every_chunk = {"write_empty_chunks": True}
    group.create_array("data/state", data=np.asarray(state, dtype=np.float32), config=every_chunk)
    group.create_array("data/action", data=np.asarray(action, dtype=np.float32), config=every_chunk)
    group.create_array("meta/episode_ends", data=np.asarray(episode_ends, dtype=np.int64), config=every_chunk)
    return path


@pytest.fixture
def tiny_zarr(tmp_path) -> Path:
    """Two episodes (3 and 4 frames); the second reaches the goal pose on its third frame."""
    far, goal = [*FAR_POSE], [*GOAL_POSE]
    blocks = [far, far, far, far, far, goal, goal]
    state = [[100.0 + i, 200.0 - i, *block] for i, block in enumerate(blocks)]
    action = [[110.0 + i, 190.0 - i] for i in range(len(blocks))]
    return write_replay_buffer(tmp_path / "tiny.zarr", state, action, [3, 7])


def load(root: Path, monkeypatch):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_OFFLINE", True)
    return LeRobotDataset("local/pusht", root=root)


def column(dataset, key: str) -> np.ndarray:
    return np.stack([np.asarray(value) for value in dataset.hf_dataset[key]])


def test_next_reward_success_and_done_describe_the_state_after_the_action(tiny_zarr, tmp_path, monkeypatch):
    root = convert_pusht_zarr(tiny_zarr, tmp_path / "out")
    dataset = load(root, monkeypatch)
    assert dataset.num_episodes == 2
    # Episode 1 reaches the goal at its frame 2, so frame 1's action leads to success; the last frame
    # has no successor and keeps its own (successful) state.
    assert column(dataset, "next.success").reshape(-1).tolist() == [False] * 3 + [False, True, True, True]
    np.testing.assert_allclose(column(dataset, "next.reward").reshape(-1), [0, 0, 0, 0, 1, 1, 1])
    assert column(dataset, "next.done").reshape(-1).tolist() == [False, False, True, False, False, False, True]


@pytest.fixture(scope="module")
def real_conversion(tmp_path_factory):
    """Demos 0 and 2 of the real replay buffer (non-adjacent, to exercise the episode slicing)."""
    if not PUSHT_ZARR.exists():
        pytest.skip(f"shared PushT demos not found at {PUSHT_ZARR}")
    root = convert_pusht_zarr(PUSHT_ZARR, tmp_path_factory.mktemp("pusht") / "local_pusht", episodes=[0, 2])
    return root, pusht_zarr.load_replay_buffer(PUSHT_ZARR)


def test_real_demos_convert_to_a_loadable_dataset(real_conversion, monkeypatch):
    root, buffer = real_conversion
    dataset = load(root, monkeypatch)
    demos = [buffer.episode(0), buffer.episode(2)]

    assert dataset.fps == 10
    assert dataset.meta.total_episodes == 2
    assert [int(n) for n in dataset.meta.episodes["length"]] == [s.stop - s.start for s in demos]
    expected_shapes = {
        "observation.state": (2,),
        "observation.environment_state": (16,),
        "action": (2,),
        "next.reward": (1,),
        "next.success": (1,),
        "next.done": (1,),
    }
    assert {key: tuple(dataset.features[key]["shape"]) for key in expected_shapes} == expected_shapes
    assert dataset.features["next.success"]["dtype"] == "bool"

    state = np.concatenate([buffer.state[s] for s in demos])
    np.testing.assert_array_equal(column(dataset, "observation.state"), state[:, :2])
    np.testing.assert_array_equal(column(dataset, "action"), np.concatenate([buffer.action[s] for s in demos]))
    keypoints, _ = keypoints_and_coverage(state[:, 2:])
    np.testing.assert_allclose(column(dataset, "observation.environment_state"), keypoints, atol=1e-3)
    assert int(column(dataset, "next.done").sum()) == 2

    frame = dataset[0]
    assert frame["task"] == TASK
    assert frame["observation.environment_state"].shape == (16,)


def test_replay_buffer_block_pose_is_the_body_origin(real_conversion):
    """Diffusion Policy's own 9 keypoints sit at fixed points on the T in the frame our pose defines.

    This pins the one assumption the env comparison cannot check: that the zarr's block x, y is the body
    origin gym_pusht's keypoints are relative to (the centre of gravity is 45 px away, along the stem).
    """
    _, buffer = real_conversion
    dp_keypoints = np.asarray(zarr.open_group(str(PUSHT_ZARR), mode="r")["data/keypoint"][:2000], np.float64)
    x, y, angle = buffer.state[:2000, 2:].astype(np.float64).T
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    dx, dy = dp_keypoints[..., 0] - x[:, None], dp_keypoints[..., 1] - y[:, None]
    local = np.stack([cos * dx + sin * dy, -sin * dx + cos * dy], axis=-1)
    assert local.std(axis=0).max() < 0.1

    corners = keypoints_and_coverage(np.zeros((1, 3)))[0].reshape(8, 2)
    tee = unary_union([Polygon(corners[:4]), Polygon(corners[4:])])
    assert max(tee.distance(Point(p)) for p in local.mean(axis=0)) < 5.0


def no_leftovers(parent: Path) -> list[str]:
    return sorted(path.name for path in parent.iterdir())


def test_missing_path_is_a_clear_error(tmp_path):
    with pytest.raises(PushTConversionError, match="does not exist"):
        convert_pusht_zarr(tmp_path / "nowhere.zarr", tmp_path / "out")
    assert no_leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["empty_dir", "missing_episode_ends"])
def test_non_replay_buffer_is_a_clear_error(tmp_path, kind):
    source = tmp_path / "source.zarr"
    if kind == "empty_dir":
        source.mkdir()
        match = "not a zarr store"
    else:
        group = zarr.open_group(str(source), mode="w", zarr_format=2)
        group.create_array("data/state", data=np.zeros((3, 5), np.float32))
        group.create_array("data/action", data=np.zeros((3, 2), np.float32))
        match = "missing array\\(s\\) meta/episode_ends"
    with pytest.raises(PushTConversionError, match=match):
        convert_pusht_zarr(source, tmp_path / "out")
    assert no_leftovers(tmp_path) == ["source.zarr"]


def test_wrong_shapes_are_a_clear_error(tmp_path):
    source = write_replay_buffer(tmp_path / "bad.zarr", np.zeros((4, 4)), np.zeros((4, 2)), [4])
    with pytest.raises(PushTConversionError, match=r"data/state has shape \(4, 4\)"):
        convert_pusht_zarr(source, tmp_path / "out")
    source = write_replay_buffer(tmp_path / "bad2.zarr", np.zeros((4, 5)), np.zeros((4, 2)), [2, 5])
    with pytest.raises(PushTConversionError, match="episode_ends"):
        convert_pusht_zarr(source, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_out_of_range_episodes_are_a_clear_error(tiny_zarr, tmp_path):
    with pytest.raises(PushTConversionError, match=r"\[2, -1\] are out of range.*2 episodes"):
        convert_pusht_zarr(tiny_zarr, tmp_path / "out", episodes=[0, 2, -1])
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_existing_output_needs_overwrite(tiny_zarr, tmp_path, monkeypatch):
    out = convert_pusht_zarr(tiny_zarr, tmp_path / "out", episodes=[0])
    (out / "keep.txt").write_text("previous")
    with pytest.raises(PushTConversionError, match="already exists.*overwrite"):
        convert_pusht_zarr(tiny_zarr, out)
    assert (out / "keep.txt").read_text() == "previous"

    convert_pusht_zarr(tiny_zarr, out, episodes=[1], overwrite=True)
    assert not (out / "keep.txt").exists()
    assert load(out, monkeypatch).num_frames == 4
    assert no_leftovers(tmp_path) == ["out", "tiny.zarr"]


def test_overwrite_refuses_a_directory_that_is_not_a_dataset(tiny_zarr, tmp_path):
    out = tmp_path / "home"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    with pytest.raises(PushTConversionError, match="is not a LeRobotDataset.*remove it yourself"):
        convert_pusht_zarr(tiny_zarr, out, overwrite=True)
    assert (out / "thesis.tex").read_text() == "years of work"
    assert no_leftovers(tmp_path) == ["home", "tiny.zarr"]


def test_a_failure_mid_conversion_leaves_nothing_behind(tiny_zarr, tmp_path, monkeypatch):
    real_episode_frames = pusht_zarr.episode_frames
    calls = []

    def fail_on_second_episode(state, action):
        calls.append(len(state))
        if len(calls) == 2:
            raise RuntimeError("disk full")
        return real_episode_frames(state, action)

    monkeypatch.setattr(pusht_zarr, "episode_frames", fail_on_second_episode)
    with pytest.raises(RuntimeError, match="disk full"):
        convert_pusht_zarr(tiny_zarr, tmp_path / "out")
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_parse_episodes():
    assert parse_episodes("0-3") == [0, 1, 2, 3]
    assert parse_episodes("0,1, 5") == [0, 1, 5]
    assert parse_episodes("0-1,7") == [0, 1, 7]
    with pytest.raises(EpisodeSelectionError, match="0-19"):
        parse_episodes("first-ten")


def test_cli_bad_input_exits_2_with_a_message(tmp_path, capsys):
    assert main([f"--zarr={tmp_path / 'nowhere.zarr'}", f"--output_root={tmp_path / 'out'}"]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_cli_takes_lists_in_lerobots_syntax_and_the_old_argparse_spellings(tiny_zarr, tmp_path, capsys, monkeypatch):
    assert main([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'a'}", "--episodes=[1]"]) == 0
    assert load(tmp_path / "a", monkeypatch).num_episodes == 1
    old = ["--zarr", str(tiny_zarr), "--output-root", str(tmp_path / "a"), "--episodes", "0-1", "--overwrite"]
    assert main(old) == 0
    assert load(tmp_path / "a", monkeypatch).num_episodes == 2


def test_cli_without_its_paths_names_both_flags(tmp_path, capsys):
    assert main([f"--output_root={tmp_path / 'out'}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-convert-pusht: error: pass --zarr=<pusht_cchi_v7_replay.zarr> and --output_root=")
    assert list(tmp_path.iterdir()) == []


def test_cli_converts_and_says_how_to_train(tiny_zarr, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    assert main([f"--zarr={tiny_zarr}", f"--output_root={out}", "--episodes=1"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and f"--dataset.root={out}" in printed
    assert load(out, monkeypatch).num_episodes == 1


# -- damaged or dangerous input, through the CLI ------------------------------------------------------------
def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    """Exit status and error line of `pacdp-convert-pusht argv`: one line after the progress bar, no traceback."""
    status = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    if status == 0:
        return status, err
    assert "Traceback" not in err and err.splitlines()[-1].startswith("pacdp-convert-pusht: error: "), err
    return status, err.splitlines()[-1]


@pytest.fixture
def copied_pusht(tmp_path, pusht_zarr) -> Path:
    """A private copy of the shared (read-only) replay buffer, to damage."""
    import shutil

    return Path(shutil.copytree(pusht_zarr, tmp_path / "pusht.zarr"))


def test_cli_refuses_a_nan_action_naming_episode_key_and_index(tiny_zarr, tmp_path, capsys):
    group = zarr.open_group(str(tiny_zarr), mode="r+")
    action = group["data/action"][...]
    action[5, 1] = np.nan  # episode 1 spans rows 3-6, so this is its frame 2
    group["data/action"][...] = action

    status, err = run_cli([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2
    assert "data/action[5, 1] is nan (episode 1, frame 2" in err and "--episodes" in err
    assert no_leftovers(tmp_path) == ["tiny.zarr"]
    # the damaged episode can be left out
    assert run_cli([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}", "--episodes=0"], capsys)[0] == 0


def test_cli_refuses_an_infinite_state(tiny_zarr, tmp_path, capsys):
    group = zarr.open_group(str(tiny_zarr), mode="r+")
    state = group["data/state"][...]
    state[1, 3] = -np.inf
    group["data/state"][...] = state
    status, err = run_cli([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2 and "data/state[1, 3] is -inf (episode 0, frame 1" in err
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_cli_refuses_a_replay_buffer_with_a_missing_chunk_file(copied_pusht, tmp_path, capsys):
    (copied_pusht / "data" / "action" / "5.0").unlink()  # zarr would read its 161 frames as (0, 0)
    status, err = run_cli([f"--zarr={copied_pusht}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2
    assert "chunk file data/action/5.0 is missing" in err and "rows 805-965" in err and "copy the replay buffer" in err
    assert no_leftovers(tmp_path) == ["pusht.zarr"]


def test_cli_names_a_garbled_chunk_without_pages_of_asyncio_noise(copied_pusht, tmp_path):
    import subprocess
    import sys

    chunk = copied_pusht / "data" / "state" / "7.0"
    chunk.write_bytes(chunk.read_bytes()[:16] + bytes(64) + chunk.read_bytes()[80:])
    result = subprocess.run(
        [sys.executable, "-m", "lerobot_pacdp.datasets.pusht_zarr", f"--zarr={copied_pusht}",
         f"--output_root={tmp_path / 'out'}"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr[-3000:]
    assert "chunk file data/state/7.0" in lines[0] and "cannot be decoded" in lines[0]
    assert no_leftovers(tmp_path) == ["pusht.zarr"]


def test_cli_refuses_a_broken_zarray_file(copied_pusht, tmp_path, capsys):
    (copied_pusht / "data" / "action" / ".zarray").write_text('{"chunks": [161, 2], "comp')
    status, err = run_cli([f"--zarr={copied_pusht}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2 and "a .zarray file) is damaged (JSONDecodeError" in err
    assert no_leftovers(tmp_path) == ["pusht.zarr"]


@pytest.mark.parametrize(
    ("output", "relation"), [(".", "is"), ("..", "contains"), ("data/converted", "lies inside")]
)
def test_cli_overwrite_never_deletes_the_input(tiny_zarr, tmp_path, capsys, output, relation):
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    status, err = run_cli([f"--zarr={tiny_zarr}", f"--output_root={tiny_zarr / output}", "--overwrite=true"], capsys)
    assert status == 2 and f"{relation} the input" in err and "outside the input" in err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    assert pusht_zarr.load_replay_buffer(tiny_zarr).num_episodes == 2


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("0-30000000", "'0-30000000' is out of range: the dataset has 2 episodes (0-1)"),
        ("1-0", "'1-0' ends before it starts; write it as 0-1"),
        ("0,x", "cannot parse episode selection"),
    ],
)
def test_cli_refuses_bad_episode_selections_before_expanding_them(tiny_zarr, tmp_path, capsys, spec, message):
    status, err = run_cli([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}", f"--episodes={spec}"], capsys)
    assert status == 2 and message in err
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_parse_episodes_refuses_ranges_beyond_any_dataset_without_expanding_them():
    with pytest.raises(EpisodeSelectionError, match="no dataset has more than 1000000 episodes"):
        parse_episodes("0-30000000")
    assert parse_episodes("3-5", num_episodes=6) == [3, 4, 5]


def test_cli_reports_a_full_disk_in_one_line_and_leaves_nothing(tiny_zarr, tmp_path, capsys, monkeypatch):
    import errno

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    def disk_full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.root / "data"))

    monkeypatch.setattr(LeRobotDataset, "save_episode", disk_full)
    status, err = run_cli([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2 and "no space left on the device" in err and "free some space" in err
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_cli_leaves_nothing_when_interrupted(tiny_zarr, tmp_path, capsys, monkeypatch):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    def interrupt(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(LeRobotDataset, "save_episode", interrupt)
    assert main([f"--zarr={tiny_zarr}", f"--output_root={tmp_path / 'out'}"]) == 130
    last_line = capsys.readouterr().err.strip().splitlines()[-1]
    assert last_line == "pacdp-convert-pusht: error: interrupted; nothing was written."
    assert no_leftovers(tmp_path) == ["tiny.zarr"]


def test_an_output_that_appears_during_the_conversion_is_kept(tiny_zarr, tmp_path, monkeypatch):
    """Two conversions racing for one output root: the later one does not replace the earlier's dataset."""
    real_write = pusht_zarr._write_dataset
    out = tmp_path / "out"

    def write_while_another_job_finishes(*args):
        real_write(*args)
        out.mkdir()
        (out / "other.txt").write_text("the other job's dataset")

    monkeypatch.setattr(pusht_zarr, "_write_dataset", write_while_another_job_finishes)
    with pytest.raises(PushTConversionError, match="appeared while converting"):
        convert_pusht_zarr(tiny_zarr, out)
    assert (out / "other.txt").read_text() == "the other job's dataset"
    assert no_leftovers(tmp_path) == ["out", "tiny.zarr"]


def test_cli_refuses_the_zip_file_itself_and_says_to_unzip_it(tmp_path, capsys):
    import zipfile

    with zipfile.ZipFile(tmp_path / "pusht.zip", "w") as archive:
        archive.writestr("pusht/pusht_cchi_v7_replay.zarr/.zgroup", '{"zarr_format": 2}')
    status, err = run_cli([f"--zarr={tmp_path / 'pusht.zip'}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert status == 2 and "pusht.zip is a file" in err and "unzip pusht.zip" in err
    assert no_leftovers(tmp_path) == ["pusht.zip"]
