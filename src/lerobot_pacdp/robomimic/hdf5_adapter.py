"""Convert a robomimic low-dim hdf5 file (any task) into a local LeRobotDataset (v3).

    pacdp-convert-robomimic --hdf5=lift/ph/low_dim.hdf5 --output_root=data/robomimic_lift
    pacdp-convert-robomimic --episodes_of=data/robomimic_lift --split=train --first=40

Features (see `tasks.py` for the layouts):
    observation.state              robot proprioception: robot0_eef_pos, robot0_eef_quat (xyzw),
                                   robot0_gripper_qpos (+ robot1_* for Transport)
    observation.environment_state  the file's `object` vector, in the layout of the robosuite generation
                                   that recorded it (feature names say which slice is which)
    action                         delta OSC_POSE actions (7-d; 14-d for Transport)
    next.reward, next.success, next.done

Episodes are the file's demos sorted like robomimic sorts them (`demo_0, demo_1, ..., demo_10, ...`), so
episode i is the i-th demo and "the first K demos" is `--dataset.episodes=[0,...,K-1]`. The file's
`mask/<filter>` splits (e.g. `train`, `valid`) are kept as episode-index lists, together with the
robosuite generation that recorded the file (which `--env.robosuite_compat` to evaluate with), in
`meta/robomimic.json`; `select_episodes` / `--episodes_of` turn them into `--dataset.episodes` lists.
"""

import contextlib
import json
import re
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_pacdp.atomic_io import staged_directory
from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli
from lerobot_pacdp.datasets import output_root_problem, quiet_dataset_writing
from lerobot_pacdp.robomimic import compat
from lerobot_pacdp.robomimic.tasks import (
    FPS,
    TASK_NAMES,
    RobomimicTask,
    get_task,
    layout_names,
    layout_slices,
    task_for_env_name,
)

METADATA_FILE = "robomimic.json"  # in the dataset's meta/ directory
METADATA_FORMAT = "lerobot_pacdp.robomimic/1"
_HINT = (
    "pass a robomimic low-dim dataset such as lift/ph/low_dim.hdf5 (robomimic's released files), or one "
    "written by pacdp-scripted-demos"
)


class RobomimicConversionError(UserInputError):
    """Bad converter input: path, file layout, task, episode selection, output directory."""


@dataclass(frozen=True)
class RobomimicFile:
    """What the converter learned about a robomimic hdf5 file (validated, nothing loaded yet)."""

    path: Path
    task: RobomimicTask
    env_args: dict[str, Any]
    generation: str  # "1.5" or "1.4" (<= 1.4)
    robosuite_version: str | None
    demos: tuple[str, ...]  # sorted like robomimic sorts them
    lengths: tuple[int, ...]
    masks: dict[str, tuple[str, ...]]
    reward_shaping: bool

    @property
    def object_layout(self) -> tuple[tuple[str, int], ...]:
        return compat.object_layout(self.task, self.generation)


def _demo_sort_key(name: str):
    match = re.fullmatch(r"demo_(\d+)", name)
    return (0, int(match.group(1)), name) if match else (1, 0, name)


def _decode(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def inspect_hdf5(hdf5_path: str | Path, task: str | None = None) -> RobomimicFile:
    """Open and validate a robomimic file without reading its arrays; errors name the problem and the fix."""
    import h5py

    path = Path(hdf5_path).expanduser()
    if not path.is_file():
        raise RobomimicConversionError(f"{path} does not exist or is not a file; {_HINT}.")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise RobomimicConversionError(f"{path} is not an HDF5 file, or a truncated one ({exc}); {_HINT}.") from None
    with f, _reading(path):
        return _inspect_open_file(path, f, task)


@contextlib.contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Turn HDF5's errors for a damaged file (OSError, KeyError, RuntimeError) into one that says so."""
    try:
        yield
    except UserInputError:
        raise
    except (OSError, KeyError, RuntimeError, ValueError) as exc:
        raise RobomimicConversionError(
            f"{path} is damaged: HDF5 cannot read part of it ({type(exc).__name__}: {exc}); copy or download the "
            "file again."
        ) from None


def _inspect_open_file(path: Path, f, task: str | None) -> RobomimicFile:
    import h5py

    data = f.get("data")
    if not isinstance(data, h5py.Group):
        raise RobomimicConversionError(
            f"{path} has no 'data' group, so it is not a robomimic dataset (top-level keys: "
            f"{sorted(f.keys())}); {_HINT}."
        )
    if "env_args" not in data.attrs:
        raise RobomimicConversionError(
            f"{path}: the 'data' group has no env_args attribute. A raw robosuite demo.hdf5 must first go "
            "through robomimic's conversion (scripts/conversion/convert_robosuite.py, then "
            "scripts/dataset_states_to_obs.py to extract low-dim observations); or " + _HINT + "."
        )
    try:
        env_args = json.loads(_decode(data.attrs["env_args"]))
        env_name = env_args["env_name"]
    except (ValueError, TypeError, KeyError) as exc:
        raise RobomimicConversionError(
            f"{path}: data.attrs['env_args'] is not robomimic's JSON with an env_name ({exc}); is the file "
            "complete?"
        ) from None
    file_task = task_for_env_name(env_name)
    if task is not None:
        wanted = get_task(task)
        if file_task is not None and file_task is not wanted:
            raise RobomimicConversionError(
                f"{path} holds {file_task.name} demos (robosuite env {env_name}), not {wanted.name}; drop "
                f"--task or pass --task={file_task.name}."
            )
        file_task = wanted
    if file_task is None:
        raise RobomimicConversionError(
            f"{path} was recorded in robosuite env {env_name!r}, which is none of the supported tasks "
            f"({', '.join(TASK_NAMES)}); pass --task to convert it as one of them."
        )

    demos = tuple(sorted((k for k in data if isinstance(data[k], h5py.Group)), key=_demo_sort_key))
    if not demos:
        raise RobomimicConversionError(f"{path} has no demonstrations under 'data'; {_HINT}.")
    lengths = tuple(_check_demo(path, data[name], name, file_task) for name in demos)

    masks: dict[str, tuple[str, ...]] = {}
    mask_group = f.get("mask")
    if isinstance(mask_group, h5py.Group):
        for name in mask_group:
            values = np.asarray(mask_group[name][()]).reshape(-1)
            masks[name] = tuple(_decode(v) for v in values)
            unknown = sorted(set(masks[name]) - set(demos), key=_demo_sort_key)
            if unknown:
                raise RobomimicConversionError(
                    f"{path}: mask/{name} lists {', '.join(unknown[:3])}{' ...' if len(unknown) > 3 else ''}, which "
                    "data/ does not hold; the file is inconsistent (robomimic's split_train_val_from_hdf5.py "
                    "rewrites the masks)."
                )
    generation, version = compat.file_generation(env_args, _attr(data, "repository_version"))
    reward_shaping = bool((env_args.get("env_kwargs") or {}).get("reward_shaping", False))
    return RobomimicFile(path, file_task, env_args, generation, version, demos, lengths, masks, reward_shaping)


def _attr(group, name: str) -> str | None:
    return _decode(group.attrs[name]) if name in group.attrs else None


def _check_demo(path: Path, demo, name: str, task: RobomimicTask) -> int:
    """Check one demo's arrays (from the hdf5 metadata only); returns its length."""
    import h5py

    where = f"{path}: data/{name}"
    actions = demo.get("actions")
    if not isinstance(actions, h5py.Dataset):
        raise RobomimicConversionError(f"{where} has no 'actions' dataset; is the file complete? {_HINT}.")
    if actions.ndim != 2 or actions.shape[1] != task.action_dim or actions.shape[0] < 1:
        raise RobomimicConversionError(
            f"{where}/actions has shape {actions.shape}, expected (T, {task.action_dim}) delta OSC_POSE actions "
            f"for {task.name}; absolute-action files (e.g. Diffusion Policy's *_abs.hdf5) are not supported, "
            "use the original low_dim.hdf5."
        )
    length = actions.shape[0]
    obs = demo.get("obs")
    if not isinstance(obs, h5py.Group):
        raise RobomimicConversionError(
            f"{where} has no 'obs' group (a states/actions-only file); extract observations with robomimic's "
            "scripts/dataset_states_to_obs.py, or " + _HINT + "."
        )
    expected = [*((key, size) for key, size in task.proprio_layout), ("object", task.object_dim)]
    missing = [key for key, _ in expected if not isinstance(obs.get(key), h5py.Dataset)]
    if missing:
        raise RobomimicConversionError(
            f"{where}/obs lacks {', '.join(missing)} (it has {', '.join(sorted(obs.keys())) or 'nothing'}); "
            f"{task.name} needs {', '.join(k for k, _ in expected)}. Is this a low-dim file of the right task?"
        )
    for key, size in expected:
        shape = obs[key].shape
        if shape != (length, size):
            what = " (robosuite's object-state for this task)" if key == "object" else ""
            raise RobomimicConversionError(
                f"{where}/obs/{key} has shape {shape}, expected ({length}, {size}){what}; the file does not "
                f"match {task.name}'s observation layout. Is --task right?"
            )
    for key in ("rewards", "dones"):
        dataset = demo.get(key)
        if not isinstance(dataset, h5py.Dataset) or dataset.shape not in ((length,), (length, 1)):
            shape = dataset.shape if isinstance(dataset, h5py.Dataset) else "missing"
            raise RobomimicConversionError(
                f"{where}/{key} is {shape}, expected ({length},); regenerate the file with robomimic's "
                "dataset_states_to_obs.py (it writes rewards and dones)."
            )
    return length


def dataset_features(info: RobomimicFile) -> dict[str, dict]:
    task = info.task
    return {
        "observation.state": {"dtype": "float32", "shape": (task.state_dim,), "names": task.state_names},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": (task.object_dim,),
            "names": layout_names(info.object_layout),
        },
        "action": {"dtype": "float32", "shape": (task.action_dim,), "names": task.action_names},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": ["reward"]},
        "next.success": {"dtype": "bool", "shape": (1,), "names": ["success"]},
        "next.done": {"dtype": "bool", "shape": (1,), "names": ["done"]},
    }


def demo_frames(demo, info: RobomimicFile) -> dict[str, np.ndarray]:
    """One demo's LeRobot feature arrays, each (T, *shape) in its declared dtype.

    `next.success` is the sparse reward of the step (robomimic's reward is r(s') = 1 on task success); with
    reward shaping (dense rewards, max 1 on success) it is reward >= 1.
    """
    task = info.task
    state = np.concatenate([_finite(info, demo, f"obs/{key}") for key in task.proprio_keys], axis=1)
    rewards = _finite(info, demo, "rewards").reshape(-1)
    success = rewards >= 1.0 - 1e-6 if info.reward_shaping else rewards > 0
    done = np.zeros(len(rewards), dtype=bool)
    done[-1] = True
    return {
        "observation.state": state.astype(np.float32),
        "observation.environment_state": _finite(info, demo, "obs/object").astype(np.float32),
        "action": _finite(info, demo, "actions").astype(np.float32),
        "next.reward": rewards.astype(np.float32)[:, None],
        "next.success": success[:, None],
        "next.done": done[:, None],
    }


def _finite(info: RobomimicFile, demo, key: str) -> np.ndarray:
    """The demo's dataset `key` as float64, refused if any value is NaN or infinite (naming the first)."""
    values = np.asarray(demo[key][()], dtype=np.float64)
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        name = demo.name.lstrip("/")
        index = ", ".join(str(int(i)) for i in bad[0])
        raise RobomimicConversionError(
            f"{info.path}: {name}/{key}[{index}] is {values[tuple(bad[0])]} ({len(bad)} non-finite value(s) in "
            f"it). Demonstrations must be finite: repair that demo, or delete it (h5py: del f['{name}']) and "
            "convert again."
        )
    return values


def dataset_metadata(info: RobomimicFile, demos: Sequence[str]) -> dict[str, Any]:
    """The content of meta/robomimic.json for a dataset holding `demos` (episode i = demos[i])."""
    index = {name: i for i, name in enumerate(demos)}
    splits = {name: [index[d] for d in mask if d in index] for name, mask in sorted(info.masks.items())}
    return {
        "format": METADATA_FORMAT,
        "task": info.task.name,
        "env_name": info.task.env_name,
        "robosuite_generation": info.generation,
        "robosuite_version": info.robosuite_version,
        "robosuite_compat": info.generation,
        "eval_hint": f"--env.type=robomimic --env.task={info.task.name} --env.robosuite_compat={info.generation}",
        "source_file": info.path.name,
        "demos": list(demos),
        "num_frames": int(sum(info.lengths[info.demos.index(d)] for d in demos)),
        "splits": splits,
        "layout": {
            "observation.state": layout_slices(info.task.proprio_layout),
            "observation.environment_state": layout_slices(info.object_layout),
        },
        "env_args": info.env_args,
    }


def convert_robomimic_hdf5(
    hdf5_path: str | Path,
    output_root: str | Path,
    repo_id: str | None = None,
    task: str | None = None,
    max_demos: int | None = None,
    overwrite: bool = False,
    *,
    progress: bool = False,
) -> Path:
    """Convert a robomimic file (all its demos, or the first `max_demos`) into a LeRobotDataset at `output_root`.

    The dataset is built in a hidden sibling directory and renamed into place once complete, so
    `output_root` is either a complete dataset or untouched (with `overwrite`, a previous dataset there is
    replaced only after the new one is complete). Returns the absolute output root.
    """
    info = inspect_hdf5(hdf5_path, task)
    demos = list(info.demos)
    if max_demos is not None:
        if max_demos < 1:
            raise RobomimicConversionError(f"--max_demos must be >= 1, got {max_demos}.")
        demos = demos[:max_demos]
    repo_id = repo_id or f"local/robomimic_{info.task.name}"
    output_root = Path(output_root).expanduser().absolute()
    problem = output_root_problem(output_root, info.path, overwrite)
    if problem:
        raise RobomimicConversionError(problem)
    try:
        with staged_directory(output_root, replace_existing=overwrite) as staging:
            _write_dataset(info, demos, staging, repo_id, progress)
            meta = staging / "meta" / METADATA_FILE
            meta.write_text(json.dumps(dataset_metadata(info, demos), indent=2) + "\n")
    except FileExistsError:
        raise RobomimicConversionError(
            f"{output_root} appeared while converting (another conversion writing it?); it was left as it is."
        ) from None
    return output_root


def _write_dataset(info: RobomimicFile, demos: Sequence[str], root: Path, repo_id: str, progress: bool) -> None:
    import h5py
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    dataset = LeRobotDataset.create(
        repo_id, fps=FPS, features=dataset_features(info), root=root, robot_type="panda", use_videos=False
    )
    try:
        with h5py.File(info.path, "r") as f:
            for name in tqdm(demos, desc=f"Converting {info.task.name} demos", unit="demo", disable=not progress):
                with _reading(info.path):
                    frames = demo_frames(f["data"][name], info)
                for t in range(len(frames["action"])):
                    frame = {key: values[t] for key, values in frames.items()}
                    dataset.add_frame(frame | {"task": info.task.description})
                dataset.save_episode()
    finally:
        # Always close the parquet writers (on failure too, so nothing is flushed into a deleted directory).
        dataset.finalize()


# ----------------------------------------------------------------------------------------------------------
# Episode selection
def load_metadata(dataset_root: str | Path) -> dict[str, Any]:
    """meta/robomimic.json of a converted dataset."""
    path = Path(dataset_root).expanduser() / "meta" / METADATA_FILE
    if not path.is_file():
        raise RobomimicConversionError(
            f"{path} not found: {dataset_root} is not a dataset written by pacdp-convert-robomimic."
        )
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RobomimicConversionError(
            f"{path} is damaged ({exc}); convert the dataset again with pacdp-convert-robomimic."
        ) from None
    if not isinstance(meta, dict) or meta.get("format") != METADATA_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise RobomimicConversionError(
            f"{path} has format {found!r}, not {METADATA_FORMAT!r}: it was written by another version of this "
            "package or by hand; convert the dataset again with this pacdp-convert-robomimic."
        )
    return meta


def select_episodes(dataset_root: str | Path, split: str | None = None, first: int | None = None) -> list[int]:
    """Episode indices for `--dataset.episodes`: the file's `split` (e.g. "train", "valid"; None = all demos),
    then its `first` K demos (the low-data experiments use 20/40/80/200)."""
    meta = load_metadata(dataset_root)
    if split is None:
        episodes = list(range(len(meta["demos"])))
    elif split in meta["splits"]:
        episodes = list(meta["splits"][split])
    else:
        available = ", ".join(meta["splits"]) or "none"
        raise RobomimicConversionError(f"the dataset has no split {split!r} (available: {available}).")
    if first is not None:
        if first < 1 or first > len(episodes):
            raise RobomimicConversionError(
                f"--first={first} is out of range: {'split ' + repr(split) if split else 'the dataset'} has "
                f"{len(episodes)} demos."
            )
        episodes = episodes[:first]
    return episodes


def episodes_argument(episodes: Sequence[int]) -> str:
    """`--dataset.episodes=[0,1,2]` for lerobot-train."""
    return "--dataset.episodes=[" + ",".join(str(int(e)) for e in episodes) + "]"


# ----------------------------------------------------------------------------------------------------------
@dataclass
class ConvertRobomimicConfig:
    """`pacdp-convert-robomimic`: convert a robomimic low-dim hdf5 file into a LeRobotDataset, or print the
    `--dataset.episodes` list of a split / first-K selection of a converted one (`--episodes_of`)."""

    hdf5: Path | None = None  # robomimic file, e.g. lift/ph/low_dim.hdf5
    output_root: Path | None = None  # the dataset directory to create
    repo_id: str | None = None  # default: local/robomimic_<task>
    task: str | None = None  # the expected task (lift, can, square, transport, tool_hang); default: the file's
    max_demos: int | None = None  # convert only the first N demos
    overwrite: bool = False  # replace a LeRobotDataset already at output_root
    episodes_of: Path | None = None  # a converted dataset: print a --dataset.episodes list of it
    split: str | None = None  # with episodes_of: a mask of the file, e.g. train or valid
    first: int | None = None  # with episodes_of: the first K demos (of the split)


def _run(cfg: ConvertRobomimicConfig) -> int:
    if cfg.episodes_of is not None:
        if cfg.hdf5 is not None or cfg.output_root is not None:
            raise UserInputError("--episodes_of does not convert: drop --hdf5/--output_root.")
        print(episodes_argument(select_episodes(cfg.episodes_of, cfg.split, cfg.first)))
        return 0
    if cfg.hdf5 is None or cfg.output_root is None:
        raise UserInputError("pass --hdf5=FILE --output_root=DIR to convert, or --episodes_of=DATASET_ROOT.")
    if cfg.split is not None or cfg.first is not None:
        raise UserInputError("--split/--first select episodes of a converted dataset: use them with --episodes_of.")
    quiet_dataset_writing()
    root = convert_robomimic_hdf5(
        cfg.hdf5, cfg.output_root, cfg.repo_id, cfg.task, cfg.max_demos, cfg.overwrite, progress=True
    )
    meta = load_metadata(root)
    repo_id = cfg.repo_id or f"local/robomimic_{meta['task']}"
    splits = ", ".join(f"{k}: {len(v)}" for k, v in meta["splits"].items()) or "none"
    print(
        f"Wrote {len(meta['demos'])} {meta['task']} demos ({meta['num_frames']} frames) as {repo_id} to {root}\n"
        f"Recorded with robosuite {meta['robosuite_version'] or meta['robosuite_generation']} "
        f"(generation {meta['robosuite_generation']}); splits: {splits}.\n"
        f"Train:    HF_HUB_OFFLINE=1 lerobot-train --policy.type=pacdp --policy.push_to_hub=false "
        f"--dataset.repo_id={repo_id} --dataset.root={root}\n"
        f"Evaluate: lerobot-eval ... {meta['eval_hint']}"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`pacdp-convert-robomimic`: exits 2 with a one-line message (no traceback) on bad input."""
    return run_draccus_cli("pacdp-convert-robomimic", ConvertRobomimicConfig, _run, argv)


if __name__ == "__main__":
    sys.exit(main())
