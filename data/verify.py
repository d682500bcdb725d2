"""Check token datasets (or any directory with a MANIFEST.json: checkpoints, tokenizers, the LAM) against the
digests recorded when they were written.

    python -m data.verify data/sample/train data/sample/val

Prints one line per file (OK, or what differs) and exits non-zero when a file is missing, truncated or corrupt.
Reads every byte once, at the disk's read speed. A directory without a manifest (published datasets, data written
before digests were recorded) only gets its metadata and file sizes checked.
"""
import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from common.cli import existing_dir, run_main
from common.errors import IntegrityError
from common.integrity import MANIFEST_NAME, check_file, list_files, read_manifest
from data.token_dataset import TokenDatasetError, read_metadata


def verify_directory(directory: Path, bar) -> int:
    """Print a line per file of `directory`; returns the number of problems."""
    problems = 0
    if (directory / "metadata.json").is_file():  # a token dataset: sizes against metadata.json
        try:
            read_metadata(directory)
        except TokenDatasetError as e:
            print(f"FAILED {e}")
            problems += 1
    try:
        files = read_manifest(directory)
    except IntegrityError as e:
        print(f"FAILED {e}")
        return problems + 1
    if files is None:
        print(f"{directory}: no {MANIFEST_NAME} (written before digests were recorded): sizes checked only")
        return problems
    for name, entry in files.items():
        problem = check_file(directory, name, entry, bar.update)
        print(f"FAILED {problem}" if problem else f"OK     {directory / name}")
        problems += problem is not None
    for name in sorted(set(list_files(directory)) - set(files)):
        print(f"note   {directory / name}: not recorded in {MANIFEST_NAME} (added later), not checked")
    return problems


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", type=existing_dir, help="Dataset (or checkpoint) directories to verify.")
    args = p.parse_args(argv)
    total = sum(e["size"] for d in args.dirs for e in (read_manifest_or_empty(d)).values())
    with tqdm(total=total, unit="B", unit_scale=True, desc="verify", file=sys.stderr) as bar:
        problems = sum(verify_directory(d, bar) for d in args.dirs)
    if problems:  # run_main's one line, exit status 1
        raise IntegrityError(f"{problems} problem(s) found; restore or re-create the files named above")
    print(f"all files match their recorded digests ({total / 1e6:.1f} MB checked)")


def read_manifest_or_empty(directory: Path) -> dict:
    try:
        return read_manifest(directory) or {}
    except IntegrityError:
        return {}


if __name__ == "__main__":
    sys.exit(run_main("data.verify", main))
