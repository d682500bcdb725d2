"""GENIE dynamics model: spatio-temporal transformer with factored logits, trained and sampled with MaskGIT."""
from common.errors import CheckpointError
from genie.config import GenieConfig, TrainingRecipe
from genie.kv_cache import TemporalKVCache
from genie.masking import MaskGITBatch, get_maskgit_collator
from genie.model import STMaskGIT
from genie.objectives import LossOutput
from genie.sampling import maskgit_sample

# inference: genie.inference.generate / teacher_forced (not exported here: genie/generate.py is the script)
__all__ = ["CheckpointError", "GenieConfig", "LossOutput", "MaskGITBatch", "STMaskGIT", "TemporalKVCache",
           "TrainingRecipe", "get_maskgit_collator", "maskgit_sample"]
