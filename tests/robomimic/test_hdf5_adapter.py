"""The robomimic hdf5 -> LeRobotDataset converter: layouts, splits, metadata, errors, CLI."""

import errno
import json

import h5py
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_pacdp.robomimic import compat, hdf5_adapter
from lerobot_pacdp.robomimic.hdf5_adapter import (
    RobomimicConversionError,
    convert_robomimic_hdf5,
    episodes_argument,
    inspect_hdf5,
    load_metadata,
    select_episodes,
)
from lerobot_pacdp.robomimic.tasks import TASKS, layout_names

from robomimic_testing import legacy_env_args, write_legacy_file

DP_OBS_DIMS = {"lift": 19, "can": 23, "square": 23, "tool_hang": 53, "transport": 59}


def _leftovers(parent, name):
    """Anything the converter left next to the output root (the output itself or a staging directory)."""
    return sorted(p.name for p in parent.iterdir() if name in p.name)


@pytest.mark.parametrize("name", list(TASKS))
def test_released_layout_file_converts_with_the_legacy_layout(tmp_path, name):
    task = TASKS[name]
    path, demos = write_legacy_file(tmp_path / f"{name}.hdf5", task, num_demos=3, length=4, env_version=None)
    root = convert_robomimic_hdf5(path, tmp_path / "dataset")
    dataset = LeRobotDataset(f"local/robomimic_{name}", root=root)
    features = dataset.meta.features
    state_dim = features["observation.state"]["shape"][0]
    env_dim = features["observation.environment_state"]["shape"][0]
    assert state_dim + env_dim == DP_OBS_DIMS[name]
    assert features["action"]["shape"] == (task.action_dim,)
    # The environment-state names follow the file's (robosuite <= 1.4) layout.
    assert features["observation.environment_state"]["names"] == layout_names(compat.legacy_object_layout(task))
    assert dataset.meta.total_episodes == 3 and dataset.meta.total_frames == 4 + 5 + 6 and dataset.fps == 20

    # Values: episode 1 = demo_1, frame by frame.
    frame = dataset[4 + 2]  # episode 1, t = 2
    demo = demos[1]
    proprio = np.concatenate([demo.obs[k][2] for k in task.proprio_keys])
    np.testing.assert_allclose(frame["observation.state"].numpy(), proprio, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(frame["observation.environment_state"].numpy(), demo.obs["object"][2], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(frame["action"].numpy(), demo.actions[2], rtol=1e-6, atol=1e-6)
    last = dataset[4 + 4]
    assert bool(last["next.success"]) and bool(last["next.done"]) and float(last["next.reward"]) == 1.0
    assert not bool(dataset[4]["next.success"]) and not bool(dataset[4]["next.done"])

    meta = load_metadata(root)
    assert meta["task"] == name and meta["robosuite_generation"] == "1.4" and meta["robosuite_version"] is None
    assert meta["robosuite_compat"] == "1.4" and "--env.robosuite_compat=1.4" in meta["eval_hint"]
    assert meta["splits"] == {"train": [0, 1], "valid": [2]}
    assert list(meta["layout"]["observation.environment_state"]) == [k for k, _ in compat.legacy_object_layout(task)]
    assert sum(b - a for a, b in meta["layout"]["observation.environment_state"].values()) == task.object_dim
    assert meta["env_args"]["env_kwargs"]["controller_configs"]["type"] == "OSC_POSE"


def test_generation_is_read_from_env_version(tmp_path):
    path, _ = write_legacy_file(tmp_path / "can.hdf5", TASKS["can"], num_demos=1, env_version="1.4.1")
    info = inspect_hdf5(path)
    assert (info.task.name, info.generation, info.robosuite_version) == ("can", "1.4", "1.4.1")


def test_demos_are_sorted_numerically_and_splits_follow_them(tmp_path):
    names = [f"demo_{i}" for i in range(12)]
    masks = {"train": [n for n in names if n not in ("demo_3", "demo_10")], "valid": ["demo_10", "demo_3"], "custom_20": names[:2]}
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=12, length=2, masks=masks)
    info = inspect_hdf5(path)
    assert info.demos == tuple(names)  # demo_10 after demo_9, as robomimic sorts them
    root = convert_robomimic_hdf5(path, tmp_path / "dataset")
    meta = load_metadata(root)
    assert meta["demos"] == names
    assert meta["splits"]["valid"] == [10, 3] and meta["splits"]["custom_20"] == [0, 1]
    assert select_episodes(root, "valid") == [10, 3]
    assert select_episodes(root, "train", first=4) == [0, 1, 2, 4]
    assert select_episodes(root, first=5) == [0, 1, 2, 3, 4]
    assert episodes_argument(select_episodes(root, first=3)) == "--dataset.episodes=[0,1,2]"
    with pytest.raises(RobomimicConversionError, match="has 2 demos"):
        select_episodes(root, "valid", first=3)
    # The selection loads in LeRobot.
    assert LeRobotDataset("local/robomimic_lift", root=root, episodes=select_episodes(root, "valid")).num_episodes == 2


def test_max_demos_keeps_the_first_demos_and_restricts_the_splits(tmp_path):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=4, length=2)
    root = convert_robomimic_hdf5(path, tmp_path / "dataset", max_demos=2)
    meta = load_metadata(root)
    assert meta["demos"] == ["demo_0", "demo_1"] and meta["splits"] == {"train": [0, 1], "valid": []}


def test_scripted_file_converts_with_the_native_layout(scripted_lift, scripted_lift_dataset):
    path, demos, _ = scripted_lift
    meta = load_metadata(scripted_lift_dataset)
    assert meta["robosuite_generation"] == "1.5" and meta["robosuite_version"].startswith("1.5")
    dataset = LeRobotDataset("local/robomimic_lift", root=scripted_lift_dataset)
    assert dataset.meta.features["observation.environment_state"]["names"] == TASKS["lift"].object_names
    assert dataset.meta.total_frames == sum(len(d) for d in demos)
    assert sorted(meta["splits"]["train"] + meta["splits"]["valid"]) == list(range(len(demos)))


# -- errors: a clear message, and nothing left behind ----------------------------------------------------
def _break(path, edit):
    with h5py.File(path, "a") as f:
        edit(f)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda f: f["data/demo_1/obs"].__delitem__("object"), r"obs lacks object"),
        (lambda f: f["data/demo_0"].__delitem__("obs"), r"no 'obs' group .*dataset_states_to_obs"),
        (lambda f: f["data/demo_1"].__delitem__("actions"), r"no 'actions' dataset"),
        (lambda f: f["data"].attrs.__delitem__("env_args"), r"no env_args attribute.*convert_robosuite"),
        (lambda f: f["data"].attrs.__setitem__("env_args", "{not json"), r"not robomimic's JSON"),
        (lambda f: f["data"].attrs.__setitem__("env_args", json.dumps({"env_name": "Stack", "env_kwargs": {}})), r"'Stack'.*--task"),
        (lambda f: f.__delitem__("data"), r"no 'data' group"),
        (lambda f: f["data/demo_0"].__delitem__("rewards"), r"rewards is missing"),
    ],
)
def test_bad_files_fail_clearly_and_leave_nothing(tmp_path, edit, message):
    path, _ = write_legacy_file(tmp_path / "can.hdf5", TASKS["can"], num_demos=2)
    _break(path, edit)
    with pytest.raises(RobomimicConversionError, match=message):
        convert_robomimic_hdf5(path, tmp_path / "out")
    assert _leftovers(tmp_path, "out") == []


def test_wrong_object_width_names_the_layout_problem(tmp_path):
    path, _ = write_legacy_file(tmp_path / "can.hdf5", TASKS["can"], num_demos=1, object_dim=10)
    with pytest.raises(RobomimicConversionError, match=r"obs/object has shape \(4, 10\), expected \(4, 14\)"):
        convert_robomimic_hdf5(path, tmp_path / "out")


def test_wrong_action_width_points_at_absolute_action_files(tmp_path):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=1)
    _break(path, lambda f: (f["data/demo_0"].__delitem__("actions"), f["data/demo_0"].create_dataset("actions", data=np.zeros((4, 10)))))
    with pytest.raises(RobomimicConversionError, match=r"\(T, 7\).*absolute-action"):
        convert_robomimic_hdf5(path, tmp_path / "out")


def test_task_mismatch_and_other_file_kinds(tmp_path):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=1)
    with pytest.raises(RobomimicConversionError, match="holds lift demos .* not square"):
        convert_robomimic_hdf5(path, tmp_path / "out", task="square")
    text = tmp_path / "notes.hdf5"
    text.write_text("hello")
    with pytest.raises(RobomimicConversionError, match="not an HDF5 file"):
        convert_robomimic_hdf5(text, tmp_path / "out")
    with pytest.raises(RobomimicConversionError, match="does not exist"):
        convert_robomimic_hdf5(tmp_path / "missing.hdf5", tmp_path / "out")
    assert _leftovers(tmp_path, "out") == []


def test_failure_while_writing_leaves_nothing_and_keeps_a_previous_dataset(tmp_path, monkeypatch):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=3)
    root = convert_robomimic_hdf5(path, tmp_path / "out")
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    with pytest.raises(RobomimicConversionError, match="already exists"):
        convert_robomimic_hdf5(path, root)

    calls = {"n": 0}
    original = LeRobotDataset.save_episode

    def flaky(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(LeRobotDataset, "save_episode", flaky)
    with pytest.raises(OSError, match="No space left"):
        convert_robomimic_hdf5(path, root, overwrite=True, max_demos=2)
    assert _leftovers(tmp_path, "out") == ["out"]  # no staging directory left
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # the old dataset is intact
    assert load_metadata(root)["demos"] == ["demo_0", "demo_1", "demo_2"]


# -- CLI -------------------------------------------------------------------------------------------------
def test_cli_converts_and_prints_episode_lists(tmp_path, capsys):
    path, _ = write_legacy_file(tmp_path / "square.hdf5", TASKS["square"], num_demos=3, env_version="1.4.1")
    assert hdf5_adapter.main([f"--hdf5={path}", f"--output_root={tmp_path / 'ds'}"]) == 0
    out = capsys.readouterr().out
    assert "Wrote 3 square demos" in out and "--env.robosuite_compat=1.4" in out and "robosuite 1.4.1" in out
    assert hdf5_adapter.main([f"--episodes_of={tmp_path / 'ds'}", "--split=train", "--first=2"]) == 0
    assert capsys.readouterr().out.strip() == "--dataset.episodes=[0,1]"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--hdf5={missing}", "--output_root={out}"], "does not exist"),
        (["--hdf5={notes}", "--output_root={out}"], "not an HDF5 file"),
        (["--output_root={out}"], "pass --hdf5=FILE --output_root=DIR"),
        (["--episodes_of={out}"], "not a dataset written by pacdp-convert-robomimic"),
        (["--hdf5={lift}", "--output_root={out}", "--task=stack"], "unknown robomimic task"),
    ],
)
def test_cli_bad_input_exits_2_without_traceback(tmp_path, capsys, argv, message):
    (tmp_path / "notes.hdf5").write_text("hello")
    lift, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=1)
    paths = {"missing": tmp_path / "missing.hdf5", "out": tmp_path / "out", "notes": tmp_path / "notes.hdf5", "lift": lift}
    assert hdf5_adapter.main([a.format(**paths) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-convert-robomimic: error:") and message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_legacy_env_args_helper_matches_released_files():
    # Guard the fixture itself: old files have a flat OSC_POSE controller config and no env_version.
    args = legacy_env_args(TASKS["transport"])
    assert args["env_kwargs"]["env_configuration"] == "single-arm-opposed" and "env_version" not in args
    assert compat.file_generation(args) == ("1.4", None)


# -- damaged or dangerous input, through the CLI ------------------------------------------------------------
def _cli_error(argv, capsys) -> str:
    """Run pacdp-convert-robomimic, expect exit 2 and return its one error line (after any progress bar)."""
    assert hdf5_adapter.main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and err.splitlines()[-1].startswith("pacdp-convert-robomimic: error: "), err
    return err.splitlines()[-1]


@pytest.mark.parametrize(
    ("key", "index", "value", "shown"),
    [("actions", (5, 0), np.nan, "actions[5, 0] is nan"), ("obs/object", (2, 7), np.inf, "obs/object[2, 7] is inf")],
)
def test_cli_refuses_non_finite_demos_naming_demo_key_and_index(tmp_path, capsys, key, index, value, shown):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=3, length=6)
    with h5py.File(path, "a") as f:
        f[f"data/demo_2/{key}"][index] = value
    err = _cli_error([f"--hdf5={path}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert f"data/demo_2/{shown} (1 non-finite value(s) in it)" in err and "del f['data/demo_2']" in err
    assert _leftovers(tmp_path, "out") == []


def test_cli_refuses_a_file_with_a_zeroed_region_in_one_line(tmp_path, capsys):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=3, length=6)
    intact = path.read_bytes()
    messages = []
    for fraction in (0.1, 0.3, 0.5, 0.7, 0.9):  # wherever the damage lands: metadata, a group, a dataset
        start = int(len(intact) * fraction)
        path.write_bytes(intact[:start] + bytes(2048) + intact[start + 2048 :])
        messages.append(_cli_error([f"--hdf5={path}", f"--output_root={tmp_path / 'out'}"], capsys))
        assert _leftovers(tmp_path, "out") == []
    assert any("is damaged: HDF5 cannot read part of it" in m and "download the file again" in m for m in messages)


@pytest.mark.parametrize(
    ("output", "relation"), [("{file}", "is"), ("{parent}", "contains"), ("{file}/x", "lies inside")]
)
def test_cli_overwrite_never_deletes_the_input(tmp_path, capsys, output, relation):
    path, _ = write_legacy_file(tmp_path / "data" / "lift.hdf5", TASKS["lift"], num_demos=2)
    before = path.read_bytes()
    output = output.format(file=path, parent=path.parent)
    err = _cli_error([f"--hdf5={path}", f"--output_root={output}", "--overwrite=true"], capsys)
    assert f"{relation} the input" in err and "outside the input" in err
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["lift.hdf5"]


def test_cli_overwrite_refuses_a_directory_that_is_not_a_dataset(tmp_path, capsys):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=1)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("keep me")
    err = _cli_error([f"--hdf5={path}", f"--output_root={tmp_path / 'out'}", "--overwrite=true"], capsys)
    assert "is not a LeRobotDataset" in err
    assert (tmp_path / "out" / "notes.txt").read_text() == "keep me"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"format": "lerobot_pacdp.robomimic/1", "demos": [', "robomimic.json is damaged"),
        ('{"format": "lerobot_pacdp.robomimic/0", "demos": []}', "format 'lerobot_pacdp.robomimic/0', not"),
        ("[1, 2]", "format 'list', not"),
    ],
)
def test_cli_refuses_a_broken_or_foreign_dataset_metadata_file(tmp_path, capsys, content, message):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=2)
    root = convert_robomimic_hdf5(path, tmp_path / "ds")
    (root / "meta" / "robomimic.json").write_text(content)
    err = _cli_error([f"--episodes_of={root}", "--split=train"], capsys)
    assert message in err and "convert the dataset again" in err


def test_cli_refuses_a_truncated_download(tmp_path, capsys):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=3)
    path.write_bytes(path.read_bytes()[:20000])
    err = _cli_error([f"--hdf5={path}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert "is not an HDF5 file, or a truncated one (" in err and "truncated file: eof = 20000" in err
    assert _leftovers(tmp_path, "out") == []


def test_cli_reports_a_full_disk_in_one_line_and_keeps_the_previous_dataset(tmp_path, capsys, monkeypatch):
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=3)
    root = convert_robomimic_hdf5(path, tmp_path / "out", max_demos=1)

    def disk_full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.root))

    monkeypatch.setattr(LeRobotDataset, "save_episode", disk_full)
    err = _cli_error([f"--hdf5={path}", f"--output_root={root}", "--overwrite=true"], capsys)
    assert "no space left on the device" in err and "free some space and run the command again" in err
    assert load_metadata(root)["demos"] == ["demo_0"] and _leftovers(tmp_path, "out") == ["out"]


def test_cli_refuses_a_split_that_lists_demos_the_file_does_not_hold(tmp_path, capsys):
    names = ["demo_0", "demo_1", "demo_7"]
    path, _ = write_legacy_file(tmp_path / "lift.hdf5", TASKS["lift"], num_demos=2, masks={"train": names})
    err = _cli_error([f"--hdf5={path}", f"--output_root={tmp_path / 'out'}"], capsys)
    assert "mask/train lists demo_7, which data/ does not hold" in err and "split_train_val_from_hdf5" in err
    assert _leftovers(tmp_path, "out") == []
