"""Error types shared by every package, so a caller catches one class whichever model raised it."""


class CheckpointError(ValueError):
    """A checkpoint whose files, kind or weights do not match what the model expects."""


class TrainingError(RuntimeError):
    """A training run that cannot go on (bad arguments for the data, too many non-finite steps, ...)."""
