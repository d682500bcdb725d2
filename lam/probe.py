"""How well latent actions predict true actions: a probe from code ids to discrete true-action labels.

True-action label of a transition (frame f - stride -> frame f) on the sample world: the button combination held
most often over the raw tics that lead from frame f - stride to frame f, i.e. button rows f - stride .. f - 1 (row t
is what was held during the tic from frame t to frame t + 1); ties go to the lowest combination id. A combination
id packs the buttons as bits: id = sum over buttons b pressed of 2^b (b in `button_names` order).

The probe: a linear classifier on one-hot codes is exactly one label per code, and the best one on the training
set is each code's most frequent label (codes never seen in training predict the overall most frequent label).
"""
import numpy as np


def button_combination_ids(buttons_Nk: np.ndarray) -> np.ndarray:
    """(N, k) 0/1 buttons -> (N,) int64 combination ids (bit b set when button b is pressed)."""
    buttons_Nk = np.asarray(buttons_Nk)
    if buttons_Nk.ndim != 2 or buttons_Nk.shape[1] > 62:
        raise ValueError(f"buttons must have shape (N, k) with k <= 62, got {buttons_Nk.shape}")
    return (buttons_Nk > 0.5).astype(np.int64) @ (1 << np.arange(buttons_Nk.shape[1], dtype=np.int64))


def combination_name(combination_id: int, button_names) -> str:
    """e.g. 5 -> 'MOVE_FORWARD+TURN_LEFT'; 0 -> 'NOOP'."""
    names = [n for b, n in enumerate(button_names) if (int(combination_id) >> b) & 1]
    return "+".join(names) or "NOOP"


def transition_labels(buttons_Nk: np.ndarray, targets: np.ndarray, stride: int) -> np.ndarray:
    """(M,) int64 label of each transition ending at a target frame: the most frequent combination id over button
    rows target - stride .. target - 1 (ties: lowest id). Needs targets >= stride."""
    targets = np.asarray(targets, dtype=np.int64)
    if len(targets) and (targets.min() < stride or targets.max() >= len(buttons_Nk)):
        raise ValueError(f"transition targets must lie in [{stride}, {len(buttons_Nk)}), "
                         f"got [{targets.min()}, {targets.max()}]")
    combos, class_N = np.unique(button_combination_ids(buttons_Nk), return_inverse=True)
    class_N = class_N.reshape(-1)
    window_MS = targets[:, None] - stride + np.arange(stride)[None, :]
    counts_MC = np.stack([(class_N[window_MS] == c).sum(axis=1) for c in range(len(combos))], axis=1)
    return combos[counts_MC.argmax(axis=1)]


def _most_frequent(labels: np.ndarray) -> int:
    values, counts = np.unique(labels, return_counts=True)
    return int(values[counts.argmax()])


def action_probe(train_codes, train_labels, val_codes, val_labels) -> dict:
    """Fit code -> label on train (per-code majority vote), score on val.

    Returns probe_acc (val accuracy of the probe), majority_rate (val accuracy of always predicting val's most
    frequent label: the best any action-blind predictor can do), train_majority_rate (val accuracy of always
    predicting train's most frequent label), mapping {code: label} and num_val.
    """
    train_codes, train_labels = np.asarray(train_codes).reshape(-1), np.asarray(train_labels).reshape(-1)
    val_codes, val_labels = np.asarray(val_codes).reshape(-1), np.asarray(val_labels).reshape(-1)
    if len(train_codes) != len(train_labels) or len(val_codes) != len(val_labels):
        raise ValueError(f"codes and labels differ in length: train {len(train_codes)} vs {len(train_labels)}, "
                         f"val {len(val_codes)} vs {len(val_labels)}")
    if len(train_codes) == 0 or len(val_codes) == 0:
        raise ValueError("action_probe needs at least one train and one val example")
    fallback = _most_frequent(train_labels)
    mapping = {int(c): _most_frequent(train_labels[train_codes == c]) for c in np.unique(train_codes)}
    predicted = np.array([mapping.get(int(c), fallback) for c in val_codes])
    return {
        "probe_acc": float((predicted == val_labels).mean()),
        "majority_rate": float((val_labels == _most_frequent(val_labels)).mean()),
        "train_majority_rate": float((val_labels == fallback).mean()),
        "mapping": mapping,
        "num_val": int(len(val_labels)),
    }
