"""The periodic validation of a training run: teacher-forced masked loss and token accuracy on fixed batches."""
import torch
from accelerate import Accelerator
from torch.utils.data import DataLoader, Dataset

from common.train_state import ResumableBatchSampler
from genie.config import GenieConfig, TrainingRecipe
from training.batches import keep_list
from training.masking import get_maskgit_collator


@torch.no_grad()
def validate(model, dataset: Dataset, config: GenieConfig, recipe: TrainingRecipe, accelerator: Accelerator,
             batch_size: int, max_batches: int, seed: int) -> dict:
    """{"val_loss", "val_acc"}: the mean over the first `max_batches` batches of `batch_size` windows per process
    (0: all of them), the same windows and masks (`seed`) every time; averaged over processes. The model is scored
    in eval mode and left in the mode it was in."""
    rank, world, device = accelerator.process_index, accelerator.num_processes, accelerator.device
    sampler = ResumableBatchSampler(len(dataset), batch_size, world, rank, seed=0, drop_last=False)
    loader = DataLoader(dataset, batch_sampler=sampler, collate_fn=keep_list, num_workers=0)
    collator = get_maskgit_collator(config, recipe, seed=seed)
    was_training = model.training
    model.eval()
    totals = torch.zeros(3, dtype=torch.float64, device=device)  # loss * B, acc * B, B
    for i, items in enumerate(loader):
        if 0 < max_batches <= i:
            break
        batch = collator(items).to(device, non_blocking=True)
        with accelerator.autocast():
            out = model(batch, recipe)
        n = len(items)
        totals += torch.stack([out.loss.double() * n, torch.as_tensor(out.acc).double().to(device) * n,
                               torch.tensor(n, dtype=torch.float64, device=device)])
    model.train(was_training)
    if world > 1:
        totals = accelerator.reduce(totals, reduction="sum")
    return {"val_loss": (totals[0] / totals[2]).item(), "val_acc": (totals[1] / totals[2]).item()}
