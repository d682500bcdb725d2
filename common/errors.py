"""Error types shared by every package, so a caller catches one class whichever model raised it."""


class CheckpointError(ValueError):
    """A checkpoint whose files, kind or weights do not match what the model expects."""


class TrainingError(RuntimeError):
    """A training run that cannot go on (bad arguments for the data, too many non-finite steps, ...)."""


class DataMismatchError(ValueError):
    """A dataset and a model (config or checkpoint), or the arguments that join them, that do not fit together:
    window length vs T, token grid vs S, vocabulary, action ids, example range."""
