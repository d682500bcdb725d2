"""MAGVIT2 image tokenizer: conv encoder, lookup-free quantizer (18 bits -> 2^18 token ids), conv decoder."""
from magvit2.config import VQConfig
from magvit2.lfq import LFQ, LFQOutput, bits_to_ids, ids_to_bits
from magvit2.model import CheckpointError, VQModel

__all__ = ["VQConfig", "VQModel", "LFQ", "LFQOutput", "CheckpointError", "bits_to_ids", "ids_to_bits"]
