"""Converters from other demonstration formats into LeRobotDatasets (PushT here, robomimic in `robomimic/`)."""

import logging
from pathlib import Path


def quiet_dataset_writing() -> None:
    """Keep a converter CLI's output to its own progress bar: no per-episode `datasets` bars, and no
    torchcodec load-failure traceback from LeRobot (it matters only for video datasets; ours have none)."""
    import datasets

    datasets.disable_progress_bars()
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)


def output_root_problem(output_root: Path, source: Path, overwrite: bool) -> str | None:
    """Why a converter must not write `output_root` from `source` (None if it may).

    The output never overlaps the input, whatever `overwrite` says (replacing the output would delete
    the input), and `overwrite` replaces only a LeRobotDataset, never an arbitrary directory or file.
    """
    output, data = output_root.resolve(), source.resolve()
    if output == data or data.is_relative_to(output) or output.is_relative_to(data):
        where = "is" if output == data else "contains" if data.is_relative_to(output) else "lies inside"
        return f"the output root {output} {where} the input {data}; choose an output root outside the input."
    if not output_root.exists() and not output_root.is_symlink():
        return None
    if not overwrite:
        return f"{output_root} already exists; choose another output root or pass --overwrite=true."
    if not (output_root / "meta" / "info.json").is_file():
        return (
            f"{output_root} exists and is not a LeRobotDataset (no meta/info.json); --overwrite=true replaces only a "
            "dataset: choose another output root or remove it yourself."
        )
    return None
