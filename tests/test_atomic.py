"""Atomic writes: an ordinary file's permissions, and nothing half-written after a failure."""
import os
import stat

import pytest

from bayespd.atomic import _UMASK, atomic_path


def test_written_file_has_ordinary_permissions(tmp_path):
    path = tmp_path / "metrics.json"
    with atomic_path(path) as tmp:
        tmp.write_text("{}")
    assert path.read_text() == "{}"
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o666 & ~_UMASK


def test_failure_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "posterior.nc"
    path.write_text("old")
    with pytest.raises(RuntimeError, match="killed"):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["posterior.nc"]
