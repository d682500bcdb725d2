"""common/allocator.py: the scripts' CPU settings keep freed memory in the process, and the environment opts out.

Each check runs in a fresh interpreter: the allocator's settings are process-wide and cannot be read back."""
import os
import platform
import subprocess
import sys

import pytest

from common.allocator import OPT_OUT_ENV

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                                reason="the settings are glibc's")

# Three 12 MiB blocks written and freed together, ten times over: under glibc's defaults the 36 MiB freed at the
# heap's top exceed its trim threshold (twice the 12 MiB its mmap threshold has risen to), so each round hands the
# pages back and faults them in again (about 9,000 faults a round); retained, the heap keeps them.
FAULTS_PER_ROUND = """
import ctypes, resource
from common.cli import apply_cpu_settings
apply_cpu_settings(0)
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
size = 12 * 2 ** 20
def one_round():
    blocks = [libc.malloc(size) for _ in range(3)]
    for block in blocks:
        ctypes.memset(block, 1, size)
    for block in blocks:
        libc.free(block)
one_round()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    one_round()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def run_python(code: str, opt_out: bool) -> str:
    env = {k: v for k, v in os.environ.items() if k != OPT_OUT_ENV}
    if opt_out:
        env[OPT_OUT_ENV] = "1"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_the_scripts_cpu_settings_reuse_freed_memory_instead_of_faulting_it_in_again():
    default = float(run_python(FAULTS_PER_ROUND, opt_out=True))
    retained = float(run_python(FAULTS_PER_ROUND, opt_out=False))
    assert default > 4000  # the pattern does fault under glibc's defaults: 36 MiB is 9,216 pages
    assert retained < default / 10


def test_the_environment_opts_out_and_the_settings_report_whether_they_took():
    code = "from common.allocator import retain_freed_memory; print(retain_freed_memory())"
    assert run_python(code, opt_out=False) == "True"
    assert run_python(code, opt_out=True) == "False"
