"""Best-of-n wall time, shared by the benchmark scripts."""
import time


def best(f, repeat: int = 5) -> float:
    """Seconds of the fastest of ``repeat`` calls of f, after one warm-up call."""
    f()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return min(times)
