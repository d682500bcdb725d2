"""GENIE dynamics model: spatio-temporal transformer with factored logits, trained and sampled with MaskGIT."""
from genie.config import GenieConfig
from genie.sampling import maskgit_sample
from genie.st_mask_git import CheckpointError, STMaskGIT, STMaskGITOutput
from genie.st_transformer import TemporalKVCache

__all__ = ["CheckpointError", "GenieConfig", "STMaskGIT", "STMaskGITOutput", "TemporalKVCache", "maskgit_sample"]
