"""Token datasets in the 1X layout: memory-mapped reader, validation and writer."""
from data.token_dataset import (RawTokenDataset, TokenDatasetError, TokenDatasetWriter, read_metadata,
                                write_token_dataset)

__all__ = ["RawTokenDataset", "TokenDatasetError", "TokenDatasetWriter", "read_metadata", "write_token_dataset"]
