"""Convert Diffusion Policy's PushT zarr replay buffer into a local LeRobotDataset (v3).

The output is laid out like the hub dataset `lerobot/pusht_keypoints`, so PAC-DP trains on the
original 206 human demos offline: agent xy as `observation.state`, the block as the 16-d T keypoints
gym_pusht observes (`obs_type="environment_state_agent_pos"`), absolute agent targets as `action`,
and gym_pusht's reward / success recomputed from the block pose.
"""

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_pacdp.atomic_io import staged_directory
from lerobot_pacdp.datasets import quiet_dataset_writing
from lerobot_pacdp.datasets.pusht_geometry import NUM_KEYPOINTS, keypoints_and_coverage, reward_and_success
from lerobot_pacdp.episodes import EpisodeSelectionError, parse_episodes

FPS = 10
TASK = "Push the T-shaped block onto the T-shaped target."
ROBOT_TYPE = "2d pointer"
REQUIRED_KEYS = ("data/state", "data/action", "meta/episode_ends")

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


class PushTConversionError(ValueError):
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
    """Read and validate the replay buffer, turning zarr failures into one-line errors that name the fix."""
    import zarr

    path = Path(zarr_path).expanduser()
    hint = "pass the pusht_cchi_v7_replay.zarr directory from Diffusion Policy's pusht.zip"
    if not path.exists():
        raise PushTConversionError(f"{path} does not exist; {hint}.")
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:
        raise PushTConversionError(f"{path} is not a zarr store ({exc}); {hint}.") from None
    missing = [key for key in REQUIRED_KEYS if not isinstance(group.get(key), zarr.Array)]
    if missing:
        raise PushTConversionError(
            f"{path} is not a Diffusion Policy replay buffer: missing array(s) {', '.join(missing)}; {hint}."
        )
    try:
        state, action, ends = (np.asarray(group[key][...]) for key in REQUIRED_KEYS)
    except Exception as exc:
        raise PushTConversionError(f"{path}: could not read the replay buffer ({exc}); is it complete?") from None

    if state.ndim != 2 or state.shape[1] != 5:
        raise PushTConversionError(
            f"{path}: data/state has shape {state.shape}, expected (N, 5) = agent x, y, block x, y, angle; "
            "is this a PushT replay buffer?"
        )
    if action.shape != (len(state), 2):
        raise PushTConversionError(
            f"{path}: data/action has shape {action.shape}, expected ({len(state)}, 2) to match data/state."
        )
    if (
        ends.ndim != 1
        or len(ends) == 0
        or not np.issubdtype(ends.dtype, np.integer)
        or ends[0] <= 0
        or np.any(np.diff(ends) <= 0)
        or ends[-1] != len(state)
    ):
        raise PushTConversionError(
            f"{path}: meta/episode_ends (shape {ends.shape}, dtype {ends.dtype}) must be strictly increasing "
            f"positive integers ending at the frame count {len(state)}; the replay buffer is corrupt."
        )
    return ReplayBuffer(state=state, action=action, episode_ends=ends)


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
    episodes: list[int] | None = None,
    overwrite: bool = False,
    *,
    progress: bool = False,
) -> Path:
    """Convert the replay buffer (or the demos listed in `episodes`, renumbered from 0) to a LeRobotDataset.

    The dataset is built in a hidden sibling directory and renamed into place only once finalized, so
    `output_root` is either a complete dataset or untouched; with `overwrite`, a previous dataset there is
    replaced only after the new one is complete. Returns the absolute output root.
    """
    buffer = load_replay_buffer(zarr_path)
    selected = _check_episodes(episodes, buffer.num_episodes)
    output_root = Path(output_root).expanduser().absolute()
    if output_root.exists() and not overwrite:
        raise PushTConversionError(
            f"{output_root} already exists; choose another output root or pass overwrite=True (--overwrite)."
        )

    from tqdm import tqdm

    with staged_directory(output_root) as staging:
        shown = tqdm(selected, desc="Converting PushT episodes", unit="episode", disable=not progress)
        _write_dataset(buffer, shown, staging, repo_id)
    return output_root


def main(argv: Sequence[str] | None = None) -> int:
    """`pacdp-convert-pusht`: exits 2 with a one-line message (no traceback) on bad input."""
    parser = argparse.ArgumentParser(
        prog="pacdp-convert-pusht",
        description="Convert Diffusion Policy's PushT zarr replay buffer into a local LeRobotDataset "
        "shaped like lerobot/pusht_keypoints.",
    )
    parser.add_argument("--zarr", required=True, type=Path, help="path to pusht_cchi_v7_replay.zarr")
    parser.add_argument("--output-root", required=True, type=Path, help="dataset directory to create")
    parser.add_argument("--repo-id", default="local/pusht", help="dataset repo id (default: local/pusht)")
    parser.add_argument("--episodes", help="demo indices to convert, e.g. 0-19 or 0,1,2 (default: all)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output root")
    args = parser.parse_args(argv)
    quiet_dataset_writing()

    try:
        episodes = parse_episodes(args.episodes) if args.episodes is not None else None
        root = convert_pusht_zarr(
            args.zarr, args.output_root, args.repo_id, episodes, args.overwrite, progress=True
        )
    except (PushTConversionError, EpisodeSelectionError) as exc:
        print(f"pacdp-convert-pusht: error: {exc}", file=sys.stderr)
        return 2
    print(f"Wrote the LeRobotDataset {args.repo_id} to {root}")
    print(
        "Train on it offline with:\n"
        f"  HF_HUB_OFFLINE=1 lerobot-train --policy.type=pacdp --policy.push_to_hub=false "
        f"--dataset.repo_id={args.repo_id} --dataset.root={root}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
