"""Atomic writes: a file or a whole directory appears complete under its final name, or not at all.

A directory written with `atomic_directory` gets a `COMPLETE` marker last; readers that see a directory without
it treat it as never written. Leftovers of killed writes are hidden `.tmp-*` entries (`remove_stale_temp_dirs`).
"""
import contextlib
import json
import os
import shutil
from pathlib import Path

COMPLETE_MARKER = "COMPLETE"
TMP_PREFIX = ".tmp-"


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_file(path, write) -> None:
    """Write one file atomically: `write(tmp_path)` fills a temporary sibling that then replaces `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_directory(final_dir):
    """Yield a temporary directory; on success mark it complete and rename it to `final_dir` (replacing it).

    On an exception the temporary directory is removed and `final_dir` is left untouched. Replacing an existing
    directory takes two renames (POSIX cannot swap directories atomically): a kill between them leaves no
    `final_dir`, never a partial one. Training checkpoints are never replaced, only new steps written.
    """
    final_dir = Path(final_dir)
    final_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp_dir = final_dir.with_name(f"{TMP_PREFIX}{final_dir.name}.{os.getpid()}")
    shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp_dir.mkdir()
    try:
        yield tmp_dir
        for f in tmp_dir.iterdir():  # data reaches the disk before the marker and the rename can
            if f.is_file():
                _fsync_path(f)
        (tmp_dir / COMPLETE_MARKER).write_text("complete\n")
        _fsync_path(tmp_dir / COMPLETE_MARKER)
        if final_dir.exists():  # rename() cannot replace a non-empty directory: move the old one aside first
            old_dir = final_dir.with_name(f"{TMP_PREFIX}old-{final_dir.name}.{os.getpid()}")
            os.replace(final_dir, old_dir)
            os.replace(tmp_dir, final_dir)
            shutil.rmtree(old_dir, ignore_errors=True)
        else:
            os.replace(tmp_dir, final_dir)
        _fsync_path(final_dir.parent)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise


def is_complete(ckpt_dir) -> bool:
    return (Path(ckpt_dir) / COMPLETE_MARKER).is_file()


def remove_stale_temp_dirs(output_dir) -> None:
    """Delete leftovers of writes that were killed half-way (hidden `.tmp-*` entries)."""
    output_dir = Path(output_dir)
    if output_dir.is_dir():
        for p in output_dir.glob(f"{TMP_PREFIX}*"):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


def write_json_atomic(path, obj) -> None:
    """Write `obj` as indented JSON to `path` atomically."""
    atomic_file(path, lambda tmp: Path(tmp).write_text(json.dumps(obj, indent=2) + "\n"))
