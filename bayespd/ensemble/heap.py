"""glibc's allocator in workers that switched off its dynamic mmap threshold.

glibc serves an allocation above M_MMAP_THRESHOLD (128 KiB at start) by a fresh mmap, whose
pages fault in on first touch, and raises the threshold as such blocks are freed, so that
a loop's large temporaries soon come from the heap. Setting any of MALLOC_TRIM_THRESHOLD_,
MALLOC_MMAP_THRESHOLD_, MALLOC_TOP_PAD_ or MALLOC_MMAP_MAX_ turns that adjustment off, and
Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536
(``distributed.nanny.pre-spawn-environ``): every torch temporary over 128 KiB (one value per
bond is 1.4 MB at 10k particles) is then a new mapping, and a realisation runs at half
speed (benchmarks/README.md, "Figures formerly in docstrings").
"""
from __future__ import annotations

import ctypes
import os

FIXED_BY = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
MMAP_THRESHOLD = 32 << 20  # glibc's largest (64-bit): blocks up to this come from the heap
TRIM_THRESHOLD = 256 << 20  # freed memory kept at the heap's top before it is returned


def keep_temporaries_on_heap() -> bool:
    """If this process fixed glibc's thresholds through the environment (``FIXED_BY``),
    raise them so that large temporaries are reused from the heap; True when changed.
    Elsewhere (glibc's own dynamic thresholds, or another C library) nothing is done."""
    if not any(name in os.environ for name in FIXED_BY):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
