"""Shape checks of observations against what a scene (or a model) predicts."""
from __future__ import annotations

import torch


def check_shape(y, expected: tuple, what: str, fix: str) -> torch.Tensor:
    """``y`` as a float64 tensor, refused with ValueError unless finite and of shape ``expected``
    (``what`` names the data, ``fix`` says how to build data that fit)."""
    y = torch.as_tensor(y, dtype=torch.float64)
    if tuple(y.shape) != tuple(expected):
        raise ValueError(f"{what} has shape {tuple(y.shape)} but the model predicts {tuple(expected)}: {fix}")
    if not bool(torch.isfinite(y).all()):
        raise ValueError(f"{what} contains NaN or inf: drop those entries or mask them (set them "
                         "to 0 where the mask is False)")
    return y
