"""The linear algebra's settings (``bayespd.linalg.config``): defaults, a block's settings
restored after it however it ends, process defaults, validation, and threads that see them."""
import dataclasses
import threading

import pytest

from bayespd import linalg
from bayespd.linalg.config import LinalgSettings


def test_defaults():
    s = LinalgSettings()
    assert (s.factor_threads, s.matvec_threads, s.cholmod_ordering) == (None, 1, "default")


def test_a_block_restores_the_settings_before_it():
    before = linalg.current_settings()
    with linalg.settings(factor_threads=1, cholmod_ordering="amd") as inside:
        assert linalg.current_settings() is inside
        assert (inside.factor_threads, inside.cholmod_ordering) == (1, "amd")
        assert inside.matvec_threads == before.matvec_threads
        with linalg.settings(factor_threads=2):
            assert linalg.current_settings().factor_threads == 2
            assert linalg.current_settings().cholmod_ordering == "amd"
        assert linalg.current_settings() is inside
    assert linalg.current_settings() is before
    with pytest.raises(RuntimeError, match="boom"):
        with linalg.settings(matvec_threads=4):
            raise RuntimeError("boom")
    assert linalg.current_settings() is before


def test_process_defaults_and_threads_that_see_them():
    """``set_defaults`` returns the settings it replaced; a thread started inside a block (as
    a lock-step job is) sees the block's settings."""
    before = linalg.set_defaults(matvec_threads=None)
    try:
        assert linalg.current_settings().matvec_threads is None
        seen = []
        with linalg.settings(factor_threads=1):
            t = threading.Thread(target=lambda: seen.append(linalg.current_settings().factor_threads))
            t.start()
            t.join()
        assert seen == [1]
    finally:
        linalg.set_defaults(**dataclasses.asdict(before))
    assert linalg.current_settings() == before


@pytest.mark.parametrize("bad", [{"factor_threads": 0}, {"matvec_threads": 1.5},
                                 {"cholmod_ordering": "rcm"}])
def test_bad_settings_are_refused_and_change_nothing(bad):
    before = linalg.current_settings()
    with pytest.raises(ValueError, match=next(iter(bad))):
        with linalg.settings(**bad):
            pass
    assert linalg.current_settings() is before
    with pytest.raises(dataclasses.FrozenInstanceError):
        before.factor_threads = 3


def test_choose_solver_by_size_backend_and_settings():
    """Direct up to the measured crossover of the backend and dimension, AMG above it; a scene
    needing the assembled K is direct at any size; the settings override both."""
    from bayespd.linalg.config import DIRECT_MAX_DOFS

    limit = DIRECT_MAX_DOFS[("splu", 2)]
    assert linalg.choose_solver(limit, 2, "splu") == "direct"
    assert linalg.choose_solver(limit + 1, 2, "splu") == "amg"
    assert linalg.choose_solver(limit + 1, 3, "splu") == "amg"  # 3D fills sooner
    assert DIRECT_MAX_DOFS[("splu", 3)] < limit <= DIRECT_MAX_DOFS[("cholmod", 2)]
    assert linalg.choose_solver(10**7, 2, "splu", needs_matrix=True) == "direct"
    with linalg.settings(direct_max_dofs=10):
        assert linalg.choose_solver(11, 2, "cholmod") == "amg"
    with linalg.settings(static_solver="direct"):
        assert linalg.choose_solver(10**7, 3, "splu") == "direct"
    with pytest.raises(ValueError, match="static_solver must be one of"):
        linalg.LinalgSettings(static_solver="cg")
    with pytest.raises(ValueError, match="direct_max_dofs"):
        linalg.LinalgSettings(direct_max_dofs=-1)
