"""Run bench_vs_reference.py, with glibc's mmap off and no trimming when S12_MALLOPT=1.

So that freed output buffers are reused without fresh page faults (README.md here).
"""

import ctypes
import os
import runpy
import sys
from pathlib import Path

if os.environ.get("S12_MALLOPT") == "1":
    libc = ctypes.CDLL("libc.so.6")
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
    assert libc.mallopt(M_MMAP_MAX, 0) == 1
    assert libc.mallopt(M_TRIM_THRESHOLD, 2**30) == 1
    print("mallopt applied", flush=True)
bench = Path(__file__).resolve().parents[2] / "bench_vs_reference.py"
sys.argv = [str(bench)] + sys.argv[1:]
runpy.run_path(str(bench), run_name="__main__")
