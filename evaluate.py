#!/usr/bin/env python
"""The 1X challenge evaluator: `./evaluate.py --val_data_dir <dir> --checkpoint_dir <dir or hub id>`.

Prints progress on stderr and, as the last line on stdout, one JSON object with loss, acc, pred_lpips, gen_time,
dec_time and num_examples. See `./evaluate.py --help`; the implementation is genie/evaluate.py (importable as
`genie.evaluate`, also runnable as `python genie/evaluate.py`).
"""
import sys

from genie.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
