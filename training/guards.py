"""The two ways a training run goes wrong that it can notice itself: NaN/inf steps and a diverged loss.

A step whose loss or gradient is NaN/inf is skipped; `NonfiniteGuard` counts them and says when too many came in a
row. A loss above twice a uniform guess's (2 ln V over V image tokens: a healthy run starts below one) means the
learning rate is too high for the model; `DivergenceGuard` counts those steps and says when the run has diverged.
Both count only steps in a row: one good step resets them.
"""
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

from common.errors import TrainingError

logger = logging.getLogger("train")


@dataclass
class NonfiniteGuard:
    """limit: skipped steps in a row that stop the run (>= 1)."""
    limit: int
    in_a_row: int = 0

    def check(self, finite: bool, step: int, loss: float) -> bool:
        """Count optimizer step `step` (1-based) as skipped unless `finite`; True when the run must stop."""
        if finite:
            self.in_a_row = 0
            return False
        self.in_a_row += 1
        logger.warning("step %d: non-finite loss (%s) or gradient; step skipped (%d in a row, limit %d)",
                       step, loss, self.in_a_row, self.limit)
        return self.in_a_row >= self.limit

    def error(self, saved_to: Path) -> TrainingError:
        return TrainingError(
            f"{self.in_a_row} optimizer steps in a row had a NaN/inf loss or gradient; stopped. The weights of the "
            f"last good step are saved in {saved_to} (lower --learning_rate, check the data, or resume from it to "
            f"skip the bad batches)")


@dataclass
class DivergenceGuard:
    """limit: diverged steps in a row that stop the run (0: never); vocab_size: the model's image tokens."""
    limit: int
    vocab_size: int
    in_a_row: int = 0

    @property
    def threshold(self) -> float:
        """Twice the loss of a uniform guess over the image tokens."""
        return 2 * math.log(self.vocab_size)

    def check(self, diverged: bool) -> bool:
        """Count a step whose loss was above `threshold` on any process; True when the run must stop."""
        self.in_a_row = self.in_a_row + 1 if diverged else 0
        return self.limit > 0 and self.in_a_row >= self.limit

    def error(self, step: int, loss: float, checkpoints: List[Tuple[int, Path]]) -> TrainingError:
        """checkpoints: the run's complete (step, path) checkpoints, oldest first."""
        first = step - self.in_a_row + 1
        last = f"the last checkpoint is {checkpoints[-1][1]}" if checkpoints else "no checkpoint was saved"
        return TrainingError(
            f"training diverged: the loss stayed above {self.threshold:.1f} (twice a uniform guess over "
            f"{self.vocab_size} tokens) from step {first} to step {step} (loss {loss:.4g}); these weights are not "
            f"saved and {last}. Lower --learning_rate or lengthen --num_warmup_steps")
