"""Converters from other demonstration formats into LeRobotDatasets (PushT here, robomimic in `robomimic/`)."""

import logging


def quiet_dataset_writing() -> None:
    """Keep a converter CLI's output to its own progress bar: no per-episode `datasets` bars, and no
    torchcodec load-failure traceback from LeRobot (it matters only for video datasets; ours have none)."""
    import datasets

    datasets.disable_progress_bars()
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
