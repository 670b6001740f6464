"""Staging directories and files of killed jobs are removed by the next write of the same output."""

import os
import subprocess
import sys
from pathlib import Path

from lerobot_pacdp.atomic_io import remove_stale_staging, staged_directory, write_text_atomic

KILLED_WRITER = """
import os, sys
from pathlib import Path
from lerobot_pacdp.atomic_io import staged_directory, staged_file
kind, target = sys.argv[1], Path(sys.argv[2])
with (staged_directory(target) if kind == "dir" else staged_file(target)) as staging:
    if kind == "dir":
        staging.mkdir()
    (staging / "half.parquet" if kind == "dir" else staging).write_text("half written")
    os.kill(os.getpid(), 9)
"""


def killed_writer_leftovers(kind: str, target: Path) -> list[Path]:
    """What a writer SIGKILLed in the middle of writing `target` leaves beside it."""
    result = subprocess.run([sys.executable, "-c", KILLED_WRITER, kind, str(target)], timeout=120)
    assert result.returncode == -9
    leftovers = [p for p in target.parent.iterdir() if p.name.startswith(f".{target.name}.")]
    assert leftovers and all(p.name.endswith(".partial") for p in leftovers)
    return leftovers


def test_a_killed_conversions_staging_directory_is_removed_by_the_next_conversion(tmp_path, capsys):
    import numpy as np
    import zarr

    from lerobot_pacdp.datasets.pusht_zarr import main

    zarr_path = tmp_path / "tiny.zarr"
    group = zarr.open_group(str(zarr_path), mode="w", zarr_format=2)
    group.create_array("data/state", data=np.tile(np.float32([1, 2, 300, 300, 0.1]), (3, 1)))
    group.create_array("data/action", data=np.tile(np.float32([1, 2]), (3, 1)))
    group.create_array("meta/episode_ends", data=np.array([3]))
    killed_writer_leftovers("dir", tmp_path / "out")
    assert main(["--zarr", str(zarr_path), "--output-root", str(tmp_path / "out")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "tiny.zarr"]


def test_a_killed_writers_staging_file_is_removed_by_the_next_write(tmp_path):
    killed_writer_leftovers("file", tmp_path / "metrics.json")
    write_text_atomic(tmp_path / "metrics.json", "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]
    assert (tmp_path / "metrics.json").read_text() == "{}"


def test_a_running_writers_staging_is_left_alone_and_an_unnamed_one_is_removed(tmp_path):
    running = tmp_path / f".out.pid{os.getpid()}.abc123.partial"
    unnamed = tmp_path / ".out.k2j3h4.partial"  # written before staging names carried a process id
    other_output = tmp_path / ".other.pid1.abc.partial"
    for path in (running, unnamed, other_output):
        path.mkdir()
    assert remove_stale_staging(tmp_path / "out") == [unnamed]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([running.name, other_output.name])


def test_a_staged_directory_replaces_an_older_output_only_when_allowed(tmp_path):
    out = tmp_path / "out"
    for replace_existing, expected in ((True, "new"), (False, "old")):
        out.mkdir(exist_ok=True)
        (out / "version.txt").write_text("old")
        try:
            with staged_directory(out, replace_existing=replace_existing) as staging:
                staging.mkdir()
                (staging / "version.txt").write_text("new")
        except FileExistsError:
            assert not replace_existing
        assert (out / "version.txt").read_text() == expected
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
