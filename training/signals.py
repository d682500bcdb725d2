"""SIGTERM as a request to stop at the next step boundary, with the training state saved (a preempted job)."""
import signal


class StopSignal:
    """While entered, a SIGTERM sets `requested` instead of killing the process; the loop checks it after each
    optimizer step, saves a checkpoint and returns. The previous handler is put back on exit."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame):
        self.requested = True  # only a flag: the handler may interrupt anything, logging included

    def __enter__(self) -> "StopSignal":
        self._previous = signal.signal(signal.SIGTERM, self._handle)
        return self

    def __exit__(self, *exc) -> bool:
        signal.signal(signal.SIGTERM, self._previous)
        return False
