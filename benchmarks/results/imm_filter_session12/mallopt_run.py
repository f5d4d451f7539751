"""Run bench_vs_reference.py with glibc's mmap disabled for large blocks (M_MMAP_MAX=0)
and no trimming, so that freed output buffers are reused without fresh page faults."""
import ctypes, runpy, sys, os
if os.environ.get("S12_MALLOPT") == "1":
    libc = ctypes.CDLL("libc.so.6")
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
    assert libc.mallopt(M_MMAP_MAX, 0) == 1
    assert libc.mallopt(M_TRIM_THRESHOLD, 2**30) == 1
    print("mallopt applied", flush=True)
sys.argv = ["bench_vs_reference.py"] + sys.argv[1:]
runpy.run_path("/work/main/benchmarks/bench_vs_reference.py", run_name="__main__")
