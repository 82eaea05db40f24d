"""A directory of finished realisations: one small ``.npz`` per realisation, written
atomically as each result arrives, so a crash loses only the realisations in flight and a
re-run skips those already on disk.

    store/plan.json            the plan the files belong to (refuses to mix plans)
    store/posterior-00017.npz  realisation 17 of the posterior ensemble
    store/mean-00003.npz       realisation 3 with parameters at the posterior mean
    store/mean-00005.err.json  a realisation that failed (kept: it would fail again)
    store/ensemble.nc          the aggregate (``stats.aggregate``)
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bayespd.atomic import atomic_path
from bayespd.validate import reading


class PlanMismatchError(ValueError):
    """The store holds realisations of a different plan."""


class EnsembleStore:
    """Realisation files under ``root`` for the plan ``plan`` (a JSON-able dict)."""

    def __init__(self, root, plan: dict):
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"the ensemble store {self.root} is a file, not a directory: pass a directory "
                             "(it is created if missing)")
        self.root.mkdir(parents=True, exist_ok=True)
        for stale in self.root.glob("*.tmp"):  # left by a crash in the middle of a write
            stale.unlink()
        path = self.root / "plan.json"
        text = json.dumps(plan, indent=1, sort_keys=True)
        if path.exists():
            with reading(path, "the store's plan (JSON)", "delete the store directory to start again"):
                old = json.loads(path.read_text())
            if old != json.loads(text):
                changed = sorted(k for k in set(old) | set(plan) if old.get(k) != plan.get(k))
                raise PlanMismatchError(
                    f"{self.root} holds realisations of another plan (differs in {changed}): "
                    "use a new directory, or delete this one to start again")
        else:
            with atomic_path(path) as tmp:
                tmp.write_text(text)

    def _path(self, kind: str, i: int, suffix: str) -> Path:
        return self.root / f"{kind}-{i:05d}{suffix}"

    def done(self, kind: str, i: int) -> bool:
        return self._path(kind, i, ".npz").exists() or self._path(kind, i, ".err.json").exists()

    def write(self, kind: str, i: int, result: dict) -> None:
        """``result``: arrays (a realisation) or ``{"error": message}`` (a failed one)."""
        if "error" in result:
            with atomic_path(self._path(kind, i, ".err.json")) as tmp:
                tmp.write_text(json.dumps(result))
            return
        with atomic_path(self._path(kind, i, ".npz")) as tmp, open(tmp, "wb") as f:
            np.savez(f, **result)

    def read(self, kind: str, i: int) -> dict:
        error = self._path(kind, i, ".err.json")
        path = error if error.exists() else self._path(kind, i, ".npz")
        with reading(path, "a stored realisation", "delete it and run the ensemble again to redo it"):
            if path == error:
                return json.loads(error.read_text())
            with np.load(path) as f:
                return {k: f[k] for k in f.files}

    def save_dataset(self, ds, name: str = "ensemble.nc") -> None:
        with atomic_path(self.root / name) as tmp:
            ds.to_netcdf(tmp, engine="h5netcdf")
