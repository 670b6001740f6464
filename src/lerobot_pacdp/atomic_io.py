"""Write-to-a-temporary-path-then-rename, so an interrupted job never leaves a half-written result.

Every file or directory this package produces (datasets, checkpoints derived from others, metrics tables,
study results) goes through these helpers: readers see either the previous complete version or the new
complete one. The temporary sibling is named `.NAME.pidPID.XXXX.partial`; a killed job cannot remove
its own, so the next write of NAME removes those whose process is gone.
"""

import contextlib
import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _staging_prefix(path: Path) -> str:
    return f".{path.name}.pid{os.getpid()}."


def _process_is_running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_stale_staging(path: str | Path) -> list[Path]:
    """Remove the temporary siblings of `path` left by killed writers; returns what was removed.

    A sibling is stale when the process named in it is no longer running (or it predates the pid in
    the name); a live writer's staging is left alone.
    """
    path = Path(path)
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(?:pid(\d+)\.)?[^.]+\.partial")
    removed = []
    with contextlib.suppress(FileNotFoundError):
        for sibling in path.parent.iterdir():
            match = pattern.fullmatch(sibling.name)
            if match is None or (match.group(1) is not None and _process_is_running(int(match.group(1)))):
                continue
            if sibling.is_dir() and not sibling.is_symlink():
                shutil.rmtree(sibling, ignore_errors=True)
            else:
                sibling.unlink(missing_ok=True)
            removed.append(sibling)
    return removed


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` to `path` via a temporary sibling file and an atomic rename."""
    with staged_file(path) as tmp:
        tmp.write_text(text)
    return Path(path)


@contextlib.contextmanager
def staged_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path to write a file to (e.g. with h5py); it replaces `path` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(path)
    fd, name = tempfile.mkstemp(prefix=_staging_prefix(path), suffix=".partial", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def staged_directory(output_root: str | Path, *, replace_existing: bool = True) -> Iterator[Path]:
    """Yield a fresh directory path to build into; it is renamed to `output_root` only on success.

    A directory already at `output_root` is replaced only once the new one is complete, and restored
    if the final rename fails. With `replace_existing=False`, one that appeared while building (another
    job writing the same output) is kept and `FileExistsError` raised instead.
    """
    output_root = Path(output_root)
    output_root.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(output_root)
    staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(output_root), suffix=".partial", dir=output_root.parent))
    try:
        yield staging / "new"
        previous = staging / "previous"
        if output_root.exists() or output_root.is_symlink():
            if not replace_existing:
                raise FileExistsError(errno.EEXIST, "appeared while this job was writing it", str(output_root))
            output_root.rename(previous)
        try:
            (staging / "new").rename(output_root)
        except BaseException:
            if previous.exists():
                previous.rename(output_root)
            raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
