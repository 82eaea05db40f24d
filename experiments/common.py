"""Helpers shared by the experiment scripts: run folders and atomic metrics files."""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from bayespd.atomic import atomic_path

# The experiments' problems are small: one thread avoids oversubscribing a 2-core machine
# (measured: tiny torch ops 10x slower with 2 threads while another process runs).
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # experiments import models/ from the repository root
    sys.path.insert(0, str(ROOT))


def run_dir(name: str) -> Path:
    path = ROOT / "runs" / name
    path.mkdir(parents=True, exist_ok=True)
    return path


def write_atomic(path: Path, text: str) -> None:
    """Write text to path via a temporary file and os.replace, so readers never see half a file."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def plain(obj):
    """numpy arrays, torch tensors and scalars inside dicts/lists as JSON lists and numbers;
    NaN and inf as null (standard JSON has no such numbers)."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, (np.ndarray, np.generic, torch.Tensor)):
        return plain(np.asarray(obj).tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_metrics(name: str, metrics: dict) -> Path:
    """runs/<name>/metrics.json with the machine and date added; prints each target
    (value, target, passed or MISSED), the count met and the wall time."""
    metrics = dict(metrics, name=name, machine=f"{platform.machine()} {os.cpu_count()} cores",
                   date=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    path = run_dir(name) / "metrics.json"
    write_atomic(path, json.dumps(plain(metrics), indent=2, default=float, allow_nan=False))
    targets = metrics.get("targets", {})
    for k, t in targets.items():
        print(f"  target {k}: {plain(t['value'])} (target {t['target']}) "
              f"{'passed' if t['passed'] else 'MISSED'}")
    print(f"{sum(bool(t['passed']) for t in targets.values())}/{len(targets)} targets met; "
          f"{metrics.get('wall_time_s', float('nan')):.1f} s; wrote {path}")
    return path


def quick_seed_arguments(doc: str, quick_help: str, switches: dict | None = None) -> argparse.Namespace:
    """The command line of an experiment that takes ``--quick``, ``--seed`` and the on/off
    ``switches`` {"--name": help}."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--seed", type=int, default=0)
    for name, text in (switches or {}).items():
        parser.add_argument(name, action="store_true", help=text)
    return parser.parse_args()
