"""Training processes keep freed memory for the next step instead of faulting it in again."""
import subprocess
import sys

import pytest

from tests.conftest import REPO

PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from tracker.training.nets.memory import keep_freed_memory
    assert keep_freed_memory()
faults = []
for _ in range(3):  # a step's buffer: allocated, written, freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(64 * 2**20 // 8)
    del a
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(faults[-1])
"""


def _faults(mode: str) -> int:
    p = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert p.returncode == 0, p.stderr
    return int(p.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_a_freed_64_mb_buffer_is_reused_without_page_faults():
    # by default the block is mapped afresh and faulted in again every time (in huge pages where
    # numpy asks for them: about 500 faults for 64 MB here); kept, the heap serves it again
    assert _faults("default") > 100
    assert _faults("keep") < 10
