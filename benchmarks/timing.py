"""Best-of-n wall time, shared by the benchmark scripts."""
import time


def best(f, repeat: int = 5) -> float:
    """Seconds of the fastest of ``repeat`` calls of f, after one warm-up call."""
    return best_with_cpu(f, repeat)[0]


def best_with_cpu(f, repeat: int = 5) -> tuple[float, float]:
    """(wall, this process's CPU) seconds of the fastest of ``repeat`` calls of f, after one warm-up call."""
    f()
    times = []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        f()
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    return min(times)
