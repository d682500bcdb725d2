"""How training and validation windows become batches: the loaders hand lists of windows to the main process,
which masks them with a seed of its own per micro-batch (training/masking.py), so that the masks depend only on
the seed and the position in the data, not on worker processes or on where a run was resumed."""
import numpy as np


def keep_list(items: list) -> list:
    """DataLoader collate_fn: the windows as they are; the (seeded) MaskGIT collator runs in the main process."""
    return items


def batch_seed(*keys: int) -> int:
    """A well-mixed 32-bit seed for one micro-batch's masking, from (seed, process, step, micro-batch)."""
    return int(np.random.SeedSequence([k & 0xFFFFFFFF for k in keys]).generate_state(1)[0])
