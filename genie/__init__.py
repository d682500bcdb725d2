"""GENIE dynamics model: spatio-temporal transformer with factored logits, trained and sampled with MaskGIT."""
from genie.config import GenieConfig

__all__ = ["GenieConfig"]
