"""The peak memory run_ccx reports is the solver's own, not the Python process's that started it."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from spinecohort.fe.calculix import exec_peak_rss_mb


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
def test_a_child_s_peak_memory_excludes_its_parent_s():
    held = np.ones(50_000_000)  # 400 MB resident in this process while the child runs
    # the child holds 120 MB of its own (plus the interpreter and numpy, ~40 MB)
    argv = [sys.executable, "-c", "import numpy, time; b = numpy.ones(15_000_000); time.sleep(0.6)"]
    proc = subprocess.Popen(argv)
    peak = 0.0
    while True:
        peak = max(peak, exec_peak_rss_mb(proc.pid, argv))
        pid, _, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        time.sleep(0.05)
    assert held.sum() == 50_000_000
    assert 120 < peak < 250
    # Linux's ru_maxrss of the child keeps the parent's pre-exec high-water mark: it would report >= 400 MB
    assert usage.ru_maxrss / 1024 > 400
    assert exec_peak_rss_mb(proc.pid, argv) == 0.0  # reaped: nothing to read
