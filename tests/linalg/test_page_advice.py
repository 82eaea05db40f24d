"""bayespd.linalg.page_advice: numpy's huge-page advice off inside the block, restored after,
also when blocks nest, overlap across threads or raise."""
import threading

import numpy as np
import pytest

from bayespd.linalg import page_advice
from bayespd.linalg.page_advice import without_huge_pages

get = getattr(np._core.multiarray, "_get_madvise_hugepage", None)
pytestmark = pytest.mark.skipif(page_advice._SWITCH is None or get is None, reason="numpy without the switch")


@pytest.mark.parametrize("advice", [True, False])
def test_advice_off_inside_and_restored_after(advice):
    before = page_advice._SWITCH(advice)
    try:
        with without_huge_pages():
            assert get() is False
            with without_huge_pages():
                assert get() is False
            assert get() is False  # the inner block left the outer one's setting
        assert get() is advice
        with pytest.raises(RuntimeError), without_huge_pages():
            raise RuntimeError("a failing build")
        assert get() is advice
    finally:
        page_advice._SWITCH(before)


def test_overlapping_blocks_on_two_threads_restore_the_advice_once_both_end():
    before = page_advice._SWITCH(True)
    inside, release, seen = threading.Event(), threading.Event(), []

    def other():
        with without_huge_pages():
            inside.set()
            release.wait(5.0)
            seen.append(get())

    try:
        thread = threading.Thread(target=other)
        thread.start()
        assert inside.wait(5.0)
        with without_huge_pages():
            pass  # ends while the other thread's block is still open
        assert get() is False
        release.set()
        thread.join()
        assert seen == [False] and get() is True
    finally:
        page_advice._SWITCH(before)


@without_huge_pages()
def _decorated():
    return get()


def test_as_a_decorator():
    assert _decorated() is False
