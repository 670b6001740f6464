"""Write-to-a-temporary-path-then-rename, so an interrupted job never leaves a half-written result.

Every file or directory this package produces (datasets, checkpoints derived from others, metrics tables,
study results) goes through these helpers: readers see either the previous complete version or the new
complete one.
"""

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` to `path` via a temporary sibling file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def staged_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path to write a file to (e.g. with h5py); it replaces `path` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        yield tmp
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def staged_directory(output_root: str | Path) -> Iterator[Path]:
    """Yield a fresh directory path to build into; it is renamed to `output_root` only on success.

    A directory already at `output_root` (the caller decides whether overwriting is allowed) is replaced
    only once the new one is complete, and restored if the final rename fails.
    """
    output_root = Path(output_root)
    output_root.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output_root.name}.", suffix=".partial", dir=output_root.parent))
    try:
        yield staging / "new"
        previous = staging / "previous"
        if output_root.exists():
            output_root.rename(previous)
        try:
            (staging / "new").rename(output_root)
        except BaseException:
            if previous.exists():
                previous.rename(output_root)
            raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
