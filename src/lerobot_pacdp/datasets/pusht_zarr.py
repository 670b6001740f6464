"""Convert Diffusion Policy's PushT zarr replay buffer into a local LeRobotDataset (v3).

The output is laid out like the hub dataset `lerobot/pusht_keypoints`, so PAC-DP trains on the
original 206 human demos offline: agent xy as `observation.state`, the block as the 16-d T keypoints
gym_pusht observes (`obs_type="environment_state_agent_pos"`), absolute agent targets as `action`,
and gym_pusht's reward / success recomputed from the block pose.
"""

import itertools
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_pacdp.atomic_io import staged_directory
from lerobot_pacdp.cli_errors import UserInputError, run_draccus_cli
from lerobot_pacdp.datasets import output_root_problem, quiet_dataset_writing
from lerobot_pacdp.datasets.pusht_geometry import NUM_KEYPOINTS, keypoints_and_coverage, reward_and_success
from lerobot_pacdp.episodes import EpisodeSelection, selected_episodes

FPS = 10
TASK = "Push the T-shaped block onto the T-shaped target."
ROBOT_TYPE = "2d pointer"
REQUIRED_KEYS = ("data/state", "data/action", "meta/episode_ends")
_HINT = "pass the pusht_cchi_v7_replay.zarr directory from Diffusion Policy's pusht.zip"

FEATURES = {
    "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
    "observation.environment_state": {
        "dtype": "float32",
        "shape": (2 * NUM_KEYPOINTS,),
        "names": [f"keypoint{i}_{axis}" for i in range(NUM_KEYPOINTS) for axis in ("x", "y")],
    },
    "action": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
    "next.reward": {"dtype": "float32", "shape": (1,), "names": ["reward"]},
    "next.success": {"dtype": "bool", "shape": (1,), "names": ["success"]},
    "next.done": {"dtype": "bool", "shape": (1,), "names": ["done"]},
}


class PushTConversionError(UserInputError):
    """Bad converter input (path, replay-buffer layout, episode selection, output directory)."""


@dataclass(frozen=True)
class ReplayBuffer:
    """The arrays of a Diffusion Policy PushT replay buffer that the conversion needs."""

    state: np.ndarray  # (N, 5): agent x, y, block x, y, block angle
    action: np.ndarray  # (N, 2): absolute agent target x, y
    episode_ends: np.ndarray  # (E,): exclusive end index of each episode

    @property
    def num_episodes(self) -> int:
        return len(self.episode_ends)

    def episode(self, index: int) -> slice:
        start = int(self.episode_ends[index - 1]) if index > 0 else 0
        return slice(start, int(self.episode_ends[index]))


def load_replay_buffer(zarr_path: str | Path) -> ReplayBuffer:
    """Read and validate the replay buffer, turning zarr failures into one-line errors that name the fix.

    zarr reads a missing chunk file as its fill value without complaint, so every chunk is checked to
    exist and read on its own (which also names a damaged one).
    """
    import zarr

    path = Path(zarr_path).expanduser()
    if not path.exists():
        raise PushTConversionError(f"{path} does not exist; {_HINT}.")
    if path.is_file():
        raise PushTConversionError(
            f"{path} is a file; a replay buffer is a directory: unzip pusht.zip and pass the "
            "pusht/pusht_cchi_v7_replay.zarr directory inside it."
        )
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:
        raise PushTConversionError(f"{path} is not a zarr store ({exc}); {_HINT}.") from None
    try:
        arrays = {key: group.get(key) for key in REQUIRED_KEYS}
    except Exception as exc:  # a damaged .zarray raises JSONDecodeError, KeyError, TypeError, ...
        raise PushTConversionError(
            f"{path}: the metadata of an array (a .zarray file) is damaged ({type(exc).__name__}: {exc}); "
            "copy the replay buffer again."
        ) from None
    missing = [key for key, array in arrays.items() if not isinstance(array, zarr.Array)]
    if missing:
        raise PushTConversionError(
            f"{path} is not a Diffusion Policy replay buffer: missing array(s) {', '.join(missing)}; {_HINT}."
        )
    state, action = arrays["data/state"], arrays["data/action"]
    if state.ndim != 2 or state.shape[1] != 5:
        raise PushTConversionError(
            f"{path}: data/state has shape {state.shape}, expected (N, 5) = agent x, y, block x, y, angle; "
            "is this a PushT replay buffer?"
        )
    if action.shape != (state.shape[0], 2):
        raise PushTConversionError(
            f"{path}: data/action has shape {action.shape}, expected ({state.shape[0]}, 2) to match data/state."
        )
    ends = _read_every_chunk(arrays["meta/episode_ends"], path)
    if (
        ends.ndim != 1
        or len(ends) == 0
        or not np.issubdtype(ends.dtype, np.integer)
        or ends[0] <= 0
        or np.any(np.diff(ends) <= 0)
        or ends[-1] != state.shape[0]
    ):
        raise PushTConversionError(
            f"{path}: meta/episode_ends (shape {ends.shape}, dtype {ends.dtype}) must be strictly increasing "
            f"positive integers ending at the frame count {state.shape[0]}; the replay buffer is corrupt."
        )
    return ReplayBuffer(state=_read_every_chunk(state, path), action=_read_every_chunk(action, path), episode_ends=ends)


def _read_every_chunk(array, store_root: Path) -> np.ndarray:
    """The array's values, read chunk by chunk from a directory store; a missing or undecodable chunk is
    an error naming it (reading one chunk at a time also keeps zarr's event loop from printing pages of
    cancelled tasks after a failure)."""
    values = np.empty(array.shape, dtype=array.dtype)
    for coords in itertools.product(*(range(n) for n in array.cdata_shape)):
        region = tuple(
            slice(i * size, min((i + 1) * size, extent)) for i, size, extent in zip(coords, array.chunks, array.shape, strict=True)
        )
        key = f"{array.path}/{array.metadata.encode_chunk_key(coords)}"
        rows = f"rows {region[0].start}-{region[0].stop - 1}"
        if not (store_root / key).is_file():
            raise PushTConversionError(
                f"{store_root}: chunk file {key} is missing, so zarr would read {rows} of {array.path} as "
                f"{array.fill_value}; the copy is incomplete: copy the replay buffer again."
            )
        try:
            values[region] = array[region]
        except Exception as exc:  # codec errors differ by compressor
            raise PushTConversionError(
                f"{store_root}: chunk file {key} ({rows} of {array.path}) cannot be decoded ({exc}); the file is "
                "damaged: copy the replay buffer again."
            ) from None
    return values


def check_finite(buffer: ReplayBuffer, episodes: Iterable[int], source: Path) -> None:
    """Refuse NaN or infinite states and actions in the selected episodes, naming the first one found."""
    for index in episodes:
        frames = buffer.episode(index)
        for key, values in (("data/state", buffer.state[frames]), ("data/action", buffer.action[frames])):
            bad = np.argwhere(~np.isfinite(values))
            if len(bad):
                frame, column = (int(n) for n in bad[0])
                raise PushTConversionError(
                    f"{source}: {key}[{frames.start + frame}, {column}] is {values[frame, column]} (episode {index}, "
                    f"frame {frame}; {len(bad)} non-finite value(s) in this episode). Demonstrations must be finite: "
                    f"repair the replay buffer or leave episode {index} out with --episodes."
                )


def episode_frames(state: np.ndarray, action: np.ndarray) -> dict[str, np.ndarray]:
    """One episode's LeRobot feature arrays, each (T, *shape) in its declared dtype.

    `next.*` describe the state reached after the frame's action, i.e. the next frame's block pose (the
    last frame, having no successor, reuses its own), matching what PushTEnv.step returns with it.
    """
    keypoints, coverage = keypoints_and_coverage(state[:, 2:5])
    reward, success = reward_and_success(np.append(coverage[1:], coverage[-1]))
    done = np.zeros(len(state), dtype=bool)
    done[-1] = True
    return {
        "observation.state": state[:, :2].astype(np.float32),
        "observation.environment_state": keypoints.astype(np.float32),
        "action": action.astype(np.float32),
        "next.reward": reward.astype(np.float32)[:, None],
        "next.success": success[:, None],
        "next.done": done[:, None],
    }


def _check_episodes(episodes: Sequence[int] | None, num_episodes: int) -> list[int]:
    if episodes is None:
        return list(range(num_episodes))
    selected = [int(index) for index in episodes]
    if not selected:
        raise PushTConversionError("no episodes selected; pass at least one episode index.")
    if len(set(selected)) != len(selected):
        raise PushTConversionError(f"episode indices must be unique; got {selected}.")
    out_of_range = [index for index in selected if not 0 <= index < num_episodes]
    if out_of_range:
        raise PushTConversionError(
            f"episode indices {out_of_range} are out of range: the replay buffer has {num_episodes} "
            f"episodes (0-{num_episodes - 1})."
        )
    return selected


def _write_dataset(buffer: ReplayBuffer, episodes: Iterable[int], root: Path, repo_id: str) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset.create(
        repo_id, fps=FPS, features=FEATURES, root=root, robot_type=ROBOT_TYPE, use_videos=False
    )
    try:
        for index in episodes:
            frame_range = buffer.episode(index)
            frames = episode_frames(buffer.state[frame_range], buffer.action[frame_range])
            for t in range(len(frames["action"])):
                dataset.add_frame({key: values[t] for key, values in frames.items()} | {"task": TASK})
            dataset.save_episode()
    finally:
        # Always close the parquet writers: on success this writes the footers LeRobot needs; on failure it
        # keeps late metadata flushes from recreating files in a staging directory we are about to delete.
        dataset.finalize()


def convert_pusht_zarr(
    zarr_path: str | Path,
    output_root: str | Path,
    repo_id: str = "local/pusht",
    episodes: EpisodeSelection | None = None,
    overwrite: bool = False,
    *,
    progress: bool = False,
) -> Path:
    """Convert the replay buffer (or the demos listed in `episodes`, renumbered from 0) to a LeRobotDataset.

    `episodes` is a list of indices or a range selection such as "0-19". The dataset is built in a hidden sibling
    directory and renamed into place only once finalized, so `output_root` is either a complete dataset or
    untouched; with `overwrite`, a previous dataset there is replaced only after the new one is complete
    (never the input, nor anything that is not a dataset). Returns the absolute output root.
    """
    source = Path(zarr_path).expanduser()
    buffer = load_replay_buffer(source)
    if isinstance(episodes, str):
        episodes = selected_episodes(episodes, buffer.num_episodes)
    selected = _check_episodes(episodes, buffer.num_episodes)
    output_root = Path(output_root).expanduser().absolute()
    problem = output_root_problem(output_root, source, overwrite)
    if problem:
        raise PushTConversionError(problem)
    check_finite(buffer, selected, source)

    from tqdm import tqdm

    try:
        with staged_directory(output_root, replace_existing=overwrite) as staging:
            shown = tqdm(selected, desc="Converting PushT episodes", unit="episode", disable=not progress)
            _write_dataset(buffer, shown, staging, repo_id)
    except FileExistsError:
        raise PushTConversionError(
            f"{output_root} appeared while converting (another conversion writing it?); it was left as it is."
        ) from None
    return output_root


@dataclass
class ConvertPushTConfig:
    """`pacdp-convert-pusht`: Diffusion Policy's PushT replay buffer -> a LeRobotDataset like lerobot/pusht_keypoints."""

    zarr: Path | None = None  # pusht_cchi_v7_replay.zarr, from Diffusion Policy's pusht.zip
    output_root: Path | None = None  # the dataset directory to create
    repo_id: str = "local/pusht"
    episodes: EpisodeSelection | None = None  # the demos to convert, 0-19 or [0,1,2] (default: all)
    overwrite: bool = False  # replace a LeRobotDataset already at output_root


def _convert_and_report(cfg: ConvertPushTConfig) -> int:
    if cfg.zarr is None or cfg.output_root is None:
        raise PushTConversionError(f"pass --zarr=<pusht_cchi_v7_replay.zarr> and --output_root=<new directory>; {_HINT}.")
    quiet_dataset_writing()
    root = convert_pusht_zarr(cfg.zarr, cfg.output_root, cfg.repo_id, cfg.episodes, cfg.overwrite, progress=True)
    print(f"Wrote the LeRobotDataset {cfg.repo_id} to {root}")
    print(
        "Train on it offline with:\n"
        f"  HF_HUB_OFFLINE=1 lerobot-train --policy.type=pacdp --policy.push_to_hub=false "
        f"--dataset.repo_id={cfg.repo_id} --dataset.root={root}"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`pacdp-convert-pusht`: exits 2 with a one-line message (no traceback) on bad input."""
    return run_draccus_cli("pacdp-convert-pusht", ConvertPushTConfig, _convert_and_report, argv)


if __name__ == "__main__":
    sys.exit(main())
