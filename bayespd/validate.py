"""Checks of user input where it enters the public API: each refuses a bad value with a
``ValueError`` (``TypeError`` for a wrong type, ``FileNotFoundError`` for a missing file)
whose message names the parameter, the value and the fix, and returns the value.
"""
from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import torch


def numbers(value, name: str = "") -> np.ndarray:
    """``value`` (a number, sequence, array or tensor) as a float numpy array."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise TypeError(f"{name + ': ' if name else ''}expected numbers, got {value!r} ({type(value).__name__})") from error


def _shown(v: np.ndarray, bad: np.ndarray) -> str:
    """A scalar as itself; an array as how many entries are bad and the first of them."""
    if v.ndim == 0:
        return f"{float(v):g}"
    k = np.unravel_index(int(np.flatnonzero(bad)[0]), v.shape)
    return f"{int(bad.sum())} of {v.size} entries, e.g. {float(v[k]):g} at index {tuple(int(i) for i in k)}"


def finite(name: str, value, fix: str = "pass finite numbers", error: type = ValueError):
    """``value`` with no NaN or inf entry; ``error`` is the class raised otherwise."""
    v = numbers(value, name)
    bad = ~np.isfinite(v)
    if bad.any():
        raise error(f"{name} contains NaN or inf ({_shown(v, bad)}): {fix}")
    return value


def positive(name: str, value, fix: str = "pass a finite positive number"):
    """``value`` finite and > 0 in every entry."""
    v = numbers(finite(name, value, fix))
    bad = ~(v > 0)
    if bad.any():
        raise ValueError(f"{name} must be positive, got {_shown(v, bad)}: {fix}")
    return value


def in_range(name: str, value, low: float, high: float, fix: str, closed: tuple = (True, True)):
    """``value`` finite and in [low, high] (``closed`` says which ends belong)."""
    v = numbers(finite(name, value, fix))
    above = v >= low if closed[0] else v > low
    below = v <= high if closed[1] else v < high
    bad = ~(above & below)
    if bad.any():
        interval = f"{'[' if closed[0] else '('}{low:g}, {high:g}{']' if closed[1] else ')'}"
        raise ValueError(f"{name} must lie in {interval}, got {_shown(v, bad)}: {fix}")
    return value


def count(name: str, value, minimum: int = 1, fix: str = "") -> int:
    """``value`` an integer (not a bool) >= ``minimum``, as an int."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r} ({type(value).__name__})")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value}" + (f": {fix}" if fix else ""))
    return int(value)


def readable_file(path, what: str) -> Path:
    """``path`` as a Path to an existing regular file (``what`` names its kind)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} {path}: check the path")
    return path


@contextlib.contextmanager
def reading(path, what: str, fix: str = "check that it is complete and of the right kind"):
    """Turn an error the dependency reading ``path`` raises (wrap only its call) into a
    ``ValueError`` that names the file; a missing file stays ``FileNotFoundError``. A
    ``SystemExit`` is caught too: meshio exits when it reads no format."""
    try:
        yield
    except FileNotFoundError:
        raise
    except (Exception, SystemExit) as error:
        raise ValueError(f"cannot read {path} as {what} ({type(error).__name__}: {error}): {fix}") from error


def device(name: str, value) -> torch.device | None:
    """``value`` (None, a string or a ``torch.device``) as a device this machine has."""
    if value is None:
        return None
    try:
        dev = torch.device(value)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"{name}={value!r} is not a torch device: use 'cpu', 'cuda' or 'cuda:<index>'") from error
    if dev.type == "cuda" and not (torch.cuda.is_available() and (dev.index or 0) < torch.cuda.device_count()):
        raise ValueError(f"{name}={value!r}: this machine has {torch.cuda.device_count()} CUDA device(s): "
                         "use 'cpu' or an index below that count")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{name}={value!r}: only 'cpu' and 'cuda' devices are supported")
    return dev
