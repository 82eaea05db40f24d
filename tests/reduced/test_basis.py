"""POD: the rank follows the discarded singular values; the basis is orthonormal and
reproduces the snapshots to the tolerance."""
import numpy as np
import pytest

from bayespd.reduced.basis import pod


def test_rank_and_reproduction(rng):
    modes = np.linalg.qr(rng.standard_normal((200, 5)))[0]
    weights = rng.standard_normal((5, 30)) * np.array([1.0, 0.3, 0.1, 1e-3, 1e-6])[:, None]
    snapshots = modes @ weights
    V, s = pod(snapshots, 1e-2)
    assert V.shape[1] == 3
    np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
    unit = snapshots / np.linalg.norm(snapshots, axis=0)
    residual = np.linalg.norm(unit - V @ (V.T @ unit)) / np.linalg.norm(unit)
    assert residual <= 1e-2
    assert pod(snapshots, 0.0)[0].shape[1] == 30


def test_a_failed_snapshot_is_refused():
    snapshots = np.ones((10, 4))
    snapshots[:, 2] = 0.0
    with pytest.raises(ValueError, match="full solve failed"):
        pod(snapshots, 1e-3)
