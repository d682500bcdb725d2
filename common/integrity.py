"""File digests for directories written as a unit (checkpoints, token datasets, the LAM, tokenizers).

When such a directory is completed, `MANIFEST.json` records the size and sha256 of each file in it:

    {"format": 1, "algorithm": "sha256",
     "files": {"model.safetensors": {"size": 1234, "sha256": "9f86d0..."}, "actions/buttons.bin": {...}}}

Loaders call `verify_manifest` on the files they read; it raises IntegrityError naming the file whose bytes changed
(silent disk or transfer corruption), and does nothing for a directory without a manifest (published checkpoints
and datasets written before digests were recorded). Files not listed in the manifest are not checked.
"""
import hashlib
import json
import os
from pathlib import Path

from common.errors import IntegrityError, writing

MANIFEST_NAME = "MANIFEST.json"
FORMAT_VERSION = 1
NOT_RECORDED = {MANIFEST_NAME, "COMPLETE"}  # the manifest itself and the completion marker (written after it)
READ_BYTES = 8 << 20  # sha256 runs at several hundred MB/s; 8 MB reads keep the disk streaming


def file_digest(path, progress=None) -> str:
    """sha256 hex digest of a file, read in 8 MB chunks; progress(n_bytes) is called after each chunk."""
    h = hashlib.sha256()
    buf = bytearray(READ_BYTES)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buf):
            h.update(view[:n])
            if progress is not None:
                progress(n)
    return h.hexdigest()


def list_files(directory) -> list:
    """Relative POSIX paths of the regular files under `directory` that a manifest records (hidden temp files,
    the manifest and the COMPLETE marker excluded), sorted."""
    directory = Path(directory)
    return sorted(p.relative_to(directory).as_posix() for p in directory.rglob("*")
                  if p.is_file() and not p.name.startswith(".") and p.name not in NOT_RECORDED)


def read_manifest(directory):
    """name -> {"size", "sha256"} from `directory/MANIFEST.json`, or None when there is none."""
    path = Path(directory) / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
        files = manifest["files"]
        if manifest.get("algorithm") != "sha256" or not isinstance(files, dict):
            raise ValueError(f"unknown algorithm {manifest.get('algorithm')!r}")
    except (ValueError, KeyError, TypeError) as e:
        raise IntegrityError(f"{path}: unreadable manifest ({e}); the directory is corrupt") from None
    return files


def update_manifest(directory, names=None) -> None:
    """Record the digests of `names` (relative paths; None: every file, replacing the whole manifest) in
    `directory/MANIFEST.json`, keeping the entries of other files. Written atomically (temp file + rename)."""
    directory = Path(directory)
    files = {} if names is None else dict(read_manifest(directory) or {})
    for name in list_files(directory) if names is None else names:
        path = directory / name
        files[name] = {"size": path.stat().st_size, "sha256": file_digest(path)}
    text = json.dumps({"format": FORMAT_VERSION, "algorithm": "sha256", "files": dict(sorted(files.items()))},
                      indent=1) + "\n"
    path = directory / MANIFEST_NAME
    tmp = directory / f".{MANIFEST_NAME}.tmp-{os.getpid()}"
    with writing("the file manifest", path):
        try:
            tmp.write_text(text)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)


def check_file(directory, name: str, entry: dict, progress=None):
    """None when `directory/name` matches its manifest entry, else a one-line description of the mismatch."""
    path = Path(directory) / name
    if not path.is_file():
        return f"{path}: missing (the manifest records {entry['size']} bytes)"
    size = path.stat().st_size
    if size != entry["size"]:  # cheap: no need to read a truncated file
        if progress is not None:
            progress(entry["size"])
        return f"{path}: {size} bytes, the manifest records {entry['size']}; the file is truncated or was replaced"
    digest = file_digest(path, progress)
    if digest != entry["sha256"]:
        return (f"{path}: contents do not match the digest recorded when it was written (sha256 {digest[:16]}... "
                f"instead of {entry['sha256'][:16]}...); the file is corrupt: restore or re-create it")
    return None


def verify_manifest(directory, names=None, progress=None) -> list:
    """Check the files `names` (None: all recorded) of `directory` against its manifest; raise IntegrityError
    naming the first file that differs. Names the manifest does not record are skipped, and so are absent files
    (the loader's own "not found" error names them better); without a manifest nothing is checked.
    Returns the names checked."""
    files = read_manifest(directory)
    if files is None:
        return []
    checked = [n for n in (files if names is None else names) if n in files and (Path(directory) / n).exists()]
    for name in checked:
        problem = check_file(directory, name, files[name], progress)
        if problem is not None:
            raise IntegrityError(problem)
    return checked
