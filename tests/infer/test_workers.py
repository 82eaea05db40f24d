"""Chains in worker processes under faults, with real processes killed by SIGKILL: a script
without a ``__main__`` guard is told to add one, a killed worker gives an error naming its
chain and a rerun resumes it, a killed parent leaves no worker behind; the resumed draws
are the uninterrupted run's, bit for bit. Every wait is bounded."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = '''
import multiprocessing, os, sys, time
from pathlib import Path
import numpy as np, pyro, pyro.distributions as dist, torch
from bayespd.infer import fit

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)
Y = 1.0 + torch.randn(20, generator=torch.Generator().manual_seed(0))


class Slow:
    """mu ~ N(0, 3), y ~ N(mu, 1), ``pause`` seconds per sampler run; a worker writes its pid
    to <folder>/<chain name>.pid."""

    def __init__(self, folder, pause):
        self.folder, self.pause = Path(folder), pause

    def __call__(self, y):
        if torch.is_grad_enabled() and self.pause:
            mark = self.folder / (multiprocessing.current_process().name + ".pid")
            if not mark.exists():
                mark.write_text(str(os.getpid()))
            time.sleep(self.pause)
        mu = pyro.sample("mu", dist.Normal(0.0, 3.0))
        with pyro.plate("obs", 20):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)


RUN = dict(num_warmup=30, num_samples=40, num_chains=2, seed=5, progress=False, checkpoint_every=5)


def main(folder, pause):
    tree = fit(Slow(folder, pause), {"y": Y}, chains="processes", checkpoint=Path(folder) / "ckpt", **RUN)
    np.save(Path(folder) / "mu.npy", tree["posterior"]["mu"].values)

'''
GUARDED = SCRIPT + 'if __name__ == "__main__":\n    main(sys.argv[1], float(sys.argv[2]))\n'
UNGUARDED = SCRIPT + "main(sys.argv[1], float(sys.argv[2]))\n"


def start(tmp_path, text, pause):
    script = tmp_path / "script.py"
    script.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, str(script), str(tmp_path), str(pause)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process, timeout=120):
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        raise
    return process.returncode, err


def wait_for(condition, timeout=60):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def gone(pid) -> bool:
    """Ended (a zombie that nobody reaped has ended too)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in "ZX"
    except FileNotFoundError:
        return True


def worker_pids(tmp_path):
    wait_for(lambda: all((tmp_path / f"chain {c}.pid").exists() for c in (0, 1)))
    return [int((tmp_path / f"chain {c}.pid").read_text()) for c in (0, 1)]


@pytest.fixture(scope="module")
def reference():
    """The uninterrupted draws, in this process (chains in processes give the same)."""
    from bayespd.infer import fit

    space = {}
    exec(SCRIPT, space)
    tree = fit(space["Slow"](".", 0.0), {"y": space["Y"]}, chains="sequential",
               **dict(space["RUN"], checkpoint_every=50))
    return tree["posterior"]["mu"].values


def test_a_script_without_main_guard_is_told_to_add_it(tmp_path):
    code, err = finish(start(tmp_path, UNGUARDED, 0.0), timeout=90)
    assert code == 1
    assert "MainGuardError" in err and 'put the script\'s work under `if __name__ == "__main__":`' in err
    assert str(tmp_path / "script.py") in err and "chains='sequential'" in err


@pytest.mark.slow
def test_a_killed_worker_names_its_chain_and_a_rerun_resumes_it(tmp_path, reference):
    """Chain 1's worker killed after its warmup: the parent ends (no hang) with an error naming
    chain 1 and its checkpoint, chain 0 has finished; the rerun gives the reference draws."""
    run = start(tmp_path, GUARDED, 0.01)
    pids = worker_pids(tmp_path)
    wait_for(lambda: (tmp_path / "ckpt" / "chain1.pt").exists())
    os.kill(pids[1], signal.SIGKILL)
    code, err = finish(run)
    assert code == 1 and "WorkerError: the worker process of chain 1 was killed by SIGKILL" in err
    assert f"{tmp_path / 'ckpt' / 'chain1.pt'} keeps its draws" in err
    assert gone(pids[0]) and gone(pids[1])
    code, err = finish(start(tmp_path, GUARDED, 0.0))
    assert code == 0, err
    assert np.array_equal(np.load(tmp_path / "mu.npy"), reference)


@pytest.mark.slow
def test_a_killed_parent_leaves_no_worker_and_a_rerun_resumes(tmp_path, reference):
    run = start(tmp_path, GUARDED, 0.01)
    pids = worker_pids(tmp_path)
    wait_for(lambda: (tmp_path / "ckpt" / "chain0.pt").exists())
    run.kill()
    run.wait(10)
    wait_for(lambda: all(gone(p) for p in pids), timeout=10)
    code, err = finish(start(tmp_path, GUARDED, 0.0))
    assert code == 0, err
    assert np.array_equal(np.load(tmp_path / "mu.npy"), reference)
