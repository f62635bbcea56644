"""flowmocap.memory: the resident size, and freed C-heap pages handed back."""

import sys

import numpy as np
import pytest

from flowmocap.memory import release_free_memory, resident_mb


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status (Linux)")
def test_freed_small_blocks_pinned_by_a_few_live_ones_are_handed_back():
    # 200 MB in 4 kB blocks (below glibc's mmap threshold: they share the heap); one in
    # 200 stays alive, so the freed pages lie between live blocks and the heap cannot
    # shrink from its top: the resident size stays up until malloc_trim hands them back
    if not release_free_memory():  # (pages freed earlier in the process would otherwise be reused unseen)
        pytest.skip("not glibc: no malloc_trim")
    before = resident_mb()
    blocks = [np.ones(4000, np.uint8) for _ in range(50000)]
    keep = blocks[::200]
    grown = resident_mb()
    assert grown - before > 150
    del blocks
    release_free_memory()
    after = resident_mb()
    assert after - before < 0.25 * (grown - before), (before, grown, after)
    assert len(keep) == 250 and all(k[0] == 1 for k in keep)  # the live blocks are intact


def test_resident_size_is_a_plausible_number():
    mb = resident_mb()
    assert np.isnan(mb) or 10 < mb < 1e6
