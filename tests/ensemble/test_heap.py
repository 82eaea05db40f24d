"""Large temporaries on the heap in workers whose environment fixed glibc's thresholds (Dask's
nanny sets MALLOC_TRIM_THRESHOLD_): a 2.4 MB array is a fresh mapping there until
``keep_temporaries_on_heap`` raises the threshold, and comes from the heap after it
(glibc's own count of mapped blocks, mallinfo2)."""
import json
import os
import platform
import subprocess
import sys

import pytest

PROBE = """
import ctypes, json, numpy as np
from bayespd.ensemble.heap import keep_temporaries_on_heap

class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
mapped = lambda: libc.mallinfo2().hblks
base = mapped()
a = np.ones(300_000)
before = mapped() - base
del a
changed = keep_temporaries_on_heap()
b = np.ones(300_000)
print(json.dumps({"before": before, "after": mapped() - base, "changed": changed}))
"""


def probe(env):
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def glibc_with_mallinfo2() -> bool:
    name, version = platform.libc_ver()
    return platform.system() == "Linux" and name == "glibc" and tuple(map(int, version.split("."))) >= (2, 33)


@pytest.mark.skipif(not glibc_with_mallinfo2(), reason="glibc >= 2.33 only (mallinfo2)")
def test_a_fixed_trim_threshold_no_longer_maps_every_large_temporary():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    fixed = probe({**env, "MALLOC_TRIM_THRESHOLD_": "65536"})
    assert fixed == {"before": 1, "after": 0, "changed": True}
    dynamic = probe(env)  # glibc's own thresholds: left alone
    assert dynamic["changed"] is False
