"""Atomic writes: a file or a whole directory appears complete under its final name, or not at all.

A directory written with `atomic_directory` gets a `MANIFEST.json` (size + sha256 of every file, see
common/integrity.py) and then a `COMPLETE` marker last; readers that see a directory without the marker treat it as
never written. Leftovers of killed writes are hidden `.tmp-*` entries (`remove_stale_temp_dirs`).
A full disk or an I/O error raises common.errors.WriteError naming what was being written and where.
"""
import contextlib
import json
import os
import shutil
from pathlib import Path

from common.errors import writing
from common.integrity import update_manifest

COMPLETE_MARKER = "COMPLETE"
TMP_PREFIX = ".tmp-"


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_file(path, write, what: str = "a file") -> None:
    """Write one file atomically: `write(tmp_path)` fills a temporary sibling that then replaces `path`.
    A disk fault raises WriteError("could not write <what> to <path>: ...") and leaves `path` as it was."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with writing(what, path):
            write(tmp)
            os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_directory(final_dir, what: str = "a directory"):
    """Yield a temporary directory; on success record its files' digests (MANIFEST.json), mark it complete and
    rename it to `final_dir` (replacing it).

    On an exception the temporary directory is removed and `final_dir` is left untouched; a disk fault becomes a
    WriteError naming `what` and `final_dir`. Replacing an existing directory takes two renames (POSIX cannot swap
    directories atomically): a kill between them leaves no `final_dir`, never a partial one. Training checkpoints
    are never replaced, only new steps written.
    """
    final_dir = Path(final_dir)
    tmp_dir = final_dir.with_name(f"{TMP_PREFIX}{final_dir.name}.{os.getpid()}")
    try:
        with writing(what, final_dir):
            final_dir.parent.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(tmp_dir, ignore_errors=True)
            tmp_dir.mkdir()
            yield tmp_dir
            update_manifest(tmp_dir)
            _complete_and_rename(tmp_dir, final_dir)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise


def _complete_and_rename(tmp_dir: Path, final_dir: Path) -> None:
    for f in tmp_dir.rglob("*"):  # data reaches the disk before the marker and the rename can
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


def write_json_atomic(path, obj, what: str = "JSON") -> None:
    """Write `obj` as indented JSON to `path` atomically (a disk fault raises WriteError)."""
    atomic_file(path, lambda tmp: Path(tmp).write_text(json.dumps(obj, indent=2) + "\n"), what)
