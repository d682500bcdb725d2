"""Token datasets in the 1X layout (memory-mapped reader, validation, writer) and the MaskGIT training collator."""
from data.collator import get_maskgit_collator
from data.token_dataset import (RawTokenDataset, TokenDatasetError, TokenDatasetWriter, read_metadata,
                                write_token_dataset)

__all__ = ["RawTokenDataset", "TokenDatasetError", "TokenDatasetWriter", "get_maskgit_collator", "read_metadata",
           "write_token_dataset"]
