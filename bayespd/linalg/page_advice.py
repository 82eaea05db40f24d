"""Large numpy arrays on small pages while the AMG path builds its operators (issue 31).

numpy asks Linux for transparent huge pages on every array of 4 MB or more (madvise
MADV_HUGEPAGE, numpy's default since 1.20). Where the kernel's THP defrag setting is "madvise"
(Debian's default: /sys/kernel/mm/transparent_hugepage/defrag), the first touch of such an array
compacts memory synchronously to find huge pages: on this project's 2-core host a fresh 107 MB
array took 257 ms to fault in against 36 ms on small pages, and a 160k-particle AMG build spent
0.4 s more CPU (system time) in K_b's assembly and the set-up's products, with no gain in the
solve (benchmarks/README.md, issue 31, ninth pass). ``without_huge_pages`` turns numpy's advice
off for a block and restores it after (nested and concurrent blocks counted), by the switch
behind numpy's NUMPY_MADVISE_HUGEPAGE; with BAYESPD_HUGE_PAGES=1 in the environment, or a numpy
without that switch, nothing changes.
"""
from __future__ import annotations

import contextlib
import os
import threading

import numpy as np

_SWITCH = None if os.environ.get("BAYESPD_HUGE_PAGES") == "1" else \
    getattr(getattr(getattr(np, "_core", None), "multiarray", None), "_set_madvise_hugepage", None)
_LOCK = threading.Lock()
_STATE = {"depth": 0, "before": None}


@contextlib.contextmanager
def without_huge_pages():
    """A context (or decorator) in which numpy allocates its large arrays without the huge-page advice."""
    if _SWITCH is None:
        yield
        return
    with _LOCK:
        if _STATE["depth"] == 0:
            _STATE["before"] = _SWITCH(False)
        _STATE["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0:
                _SWITCH(_STATE["before"])
