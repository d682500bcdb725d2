"""GENIE dynamics model: spatio-temporal transformer with factored logits, trained and sampled with MaskGIT.

Importing the package loads only the network (genie.model and what it needs); the training collator
(training.masking), the sampler (genie.sampling), inference (genie.inference) and the scripts are imported by name.
"""
from common.errors import CheckpointError
from genie.config import GenieConfig, TrainingRecipe
from genie.model import LossOutput, MaskGITBatch, STMaskGIT
from genie.transformer import TemporalKVCache

__all__ = ["CheckpointError", "GenieConfig", "LossOutput", "MaskGITBatch", "STMaskGIT", "TemporalKVCache",
           "TrainingRecipe"]
