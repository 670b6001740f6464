"""The datasets of a study: where each task's LeRobotDataset lives, how many demos it has, converting PushT's,
and a fingerprint of its values (which recording of the demos a run trained on)."""

import hashlib
import json
import logging
import time
from pathlib import Path

from lerobot_pacdp.study.presets import StudyError, TaskPreset

logger = logging.getLogger("pacdp-study")


def dataset_root(task: TaskPreset, output_dir: Path) -> Path | None:
    """Where the task's dataset lives (None: LeRobot's default location for its repo id)."""
    if task.dataset_root is None:
        return None
    root = Path(task.dataset_root)
    return root if root.is_absolute() else output_dir / root


def _dataset_location(task: TaskPreset, output_dir: Path) -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return dataset_root(task, output_dir) or HF_LEROBOT_HOME / task.repo_id


def dataset_fingerprint(task: TaskPreset, output_dir: Path) -> str | None:
    """A hash of every value of the task's dataset under `output_dir` (None: not there). Values, not file
    bytes (those carry the writer's version), so two recordings of the demos hash apart if they differ
    anywhere, down to a float's last bit, as recordings made with other BLAS kernels do."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = sorted((_dataset_location(task, output_dir) / "data").rglob("*.parquet"))
    if not files:
        return None
    digest = hashlib.sha256()
    for file in files:
        table = pq.read_table(file)
        for name in sorted(table.column_names):
            values = table.column(name).combine_chunks()
            while isinstance(values, pa.ListArray | pa.LargeListArray | pa.FixedSizeListArray):
                values = values.flatten()  # a state or an action: its scalars
            array = values.to_numpy(zero_copy_only=False)
            digest.update(f"{name}:{array.dtype}:{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def _missing_pusht_zarr(task: TaskPreset, root: Path) -> StudyError:
    return StudyError(
        f"{task.name}: no dataset at {root} and no PushT replay buffer to convert it from; pass "
        "--pusht_zarr=<pusht_cchi_v7_replay.zarr> (from Diffusion Policy's pusht.zip)."
    )


def count_episodes(task: TaskPreset, output_dir: Path, pusht_zarr: Path | None) -> int:
    """Demos in the task's dataset (or in the PushT replay buffer it will be converted from)."""
    root = _dataset_location(task, output_dir)
    info = root / "meta" / "info.json"
    if info.is_file():
        return int(json.loads(info.read_text())["total_episodes"])
    if task.from_pusht_zarr:
        if pusht_zarr is None:
            raise _missing_pusht_zarr(task, root)
        from lerobot_pacdp.datasets.pusht_zarr import load_replay_buffer

        return load_replay_buffer(pusht_zarr).num_episodes
    if task.scripted is not None:
        return task.scripted.num_demos
    if task.num_episodes is not None:
        return task.num_episodes
    raise StudyError(f"{task.name}: no dataset at {root}; convert its demos there first.")


def prepare_dataset(task: TaskPreset, output_dir: Path, pusht_zarr: Path | None) -> None:
    """Record a scripted task's demos, or convert the PushT demos, into the study's output dir once (all of
    them: indices stay the source's)."""
    root = _dataset_location(task, output_dir)
    if (root / "meta" / "info.json").is_file():
        return
    if task.scripted is not None:
        _record_scripted(task, root)
        return
    if not task.from_pusht_zarr:
        raise StudyError(
            f"{task.name}: the dataset {task.repo_id} is missing at {root}; convert it first "
            "(pacdp-convert-robomimic for robomimic tasks)."
        )
    if pusht_zarr is None:
        raise _missing_pusht_zarr(task, root)
    from lerobot_pacdp.datasets.pusht_zarr import convert_pusht_zarr

    logger.info("converting the PushT demos of %s into %s ...", pusht_zarr, root)
    start = time.monotonic()
    convert_pusht_zarr(pusht_zarr, root, task.repo_id)
    logger.info("converted in %.0f s", time.monotonic() - start)


def _record_scripted(task: TaskPreset, root: Path) -> None:
    from lerobot_pacdp.robomimic.hdf5_adapter import convert_robomimic_hdf5, inspect_hdf5
    from lerobot_pacdp.robomimic.scripted_experts import ScriptedDemosConfig, record_scripted_demos

    scripted = task.scripted
    hdf5 = root.with_suffix(".hdf5")
    logger.info("recording %d scripted %s demos into %s ...", scripted.num_demos, task.name, hdf5)
    start = time.monotonic()
    record_scripted_demos(ScriptedDemosConfig(
        task=task.name, num_demos=scripted.num_demos, output=hdf5, seed=scripted.seed,
        action_noise=scripted.action_noise, overwrite=True,
    ))  # fmt: skip
    recorded = len(inspect_hdf5(hdf5, task.name).demos)
    if recorded != scripted.num_demos:
        raise StudyError(f"{task.name}: the scripted expert recorded {recorded} of {scripted.num_demos} demos; "
                         "lower the preset's action noise or record fewer.")  # fmt: skip
    convert_robomimic_hdf5(hdf5, root, task.repo_id, task.name)
    logger.info("recorded and converted in %.0f s", time.monotonic() - start)
