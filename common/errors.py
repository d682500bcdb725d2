"""Error types shared by every package, so a caller catches one class whichever model raised it."""
import contextlib
import errno
import os

# errno values that mean the disk (not the caller) failed a write: full, over quota, read-only, broken, too big.
DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG}


class InputError(ValueError):
    """Bad input a user can fix (a flag value, a file, a config, a dataset): a script ends on its message, one line,
    with no traceback (`common.cli.run_main`)."""


class CheckpointError(InputError):
    """A checkpoint whose files, kind or weights do not match what the model expects."""


class IntegrityError(CheckpointError):
    """A file whose bytes differ from the digest recorded in its directory's MANIFEST.json when it was written."""


class TrainingError(RuntimeError):
    """A training run that cannot go on (bad arguments for the data, too many non-finite steps, ...)."""


class DataMismatchError(InputError):
    """A dataset and a model (config or checkpoint), or the arguments that join them, that do not fit together:
    window length vs T, token grid vs S, vocabulary, action ids, example range."""


class WriteError(OSError):
    """A write that the disk refused (full, over quota, read-only, I/O error); str() is one line naming what was
    being written and where. Nothing half-written is left under the final name."""

    def __init__(self, message: str, code=None):
        super().__init__(message)
        self.errno = code


def disk_fault(exc: BaseException):
    """(errno, reason) when `exc` is a disk fault, else None. safetensors wraps OS errors in its own
    SafetensorError whose text carries "(os error N)"; that is recognized too."""
    if isinstance(exc, OSError) and exc.errno in DISK_ERRNOS:
        return exc.errno, os.strerror(exc.errno)
    text = str(exc)
    for code in DISK_ERRNOS:
        if f"os error {code})" in text:
            return code, os.strerror(code)
    return None


@contextlib.contextmanager
def writing(what: str, path):
    """Turn a disk fault raised inside the block into a WriteError "could not write <what> to <path>: <reason>"."""
    try:
        yield
    except WriteError:
        raise
    except Exception as e:
        fault = disk_fault(e)
        if fault is None:
            raise
        raise WriteError(f"could not write {what} to {path}: {fault[1]}", fault[0]) from e
