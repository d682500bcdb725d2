"""Shared pytest fixtures; the suite runs on the CPU."""
import os

import pytest
import torch

# The suite pins the CPU even on a GPU box: the scripts pick CUDA when they see it, and the resume tests compare
# weights bit for bit, which CUDA's nondeterministic kernels do not give. Set before anything initializes CUDA;
# subprocesses (train.py, run_sample.sh) inherit it. The value found at start-up is kept for tests that want it.
os.environ.setdefault("GENIE_TEST_CUDA_VISIBLE_DEVICES", os.environ.get("CUDA_VISIBLE_DEVICES", "unset"))
os.environ["CUDA_VISIBLE_DEVICES"] = ""


@pytest.fixture(scope="module")
def one_thread():
    """Tiny models run fastest on one thread, and the test machine's cores are shared; restores the count after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
