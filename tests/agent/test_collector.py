"""The agent's cyclic garbage collector runs only at safe points, and the process's collector is restored after."""

from __future__ import annotations

import gc
import weakref

from agent.collector import SafePointCollector


class _Node:
    def __init__(self) -> None:
        self.other: _Node | None = None


def _cycles(n: int) -> list[weakref.ref]:
    """``n`` unreachable reference cycles (only the collector frees them); weak references to one node of each."""
    refs = []
    for _ in range(n):
        a, b = _Node(), _Node()
        a.other, b.other = b, a
        refs.append(weakref.ref(a))
    return refs


def test_no_collection_between_safe_points_and_the_due_one_at_the_next() -> None:
    started: list[int] = []

    def seen(phase: str, info: dict) -> None:
        if phase == "start":
            started.append(info["generation"])

    was_enabled = gc.isenabled()
    gc.callbacks.append(seen)
    try:
        with SafePointCollector() as collector:
            assert not gc.isenabled()
            assert gc.get_freeze_count() > 0  # what was alive at the start is out of the collector's walks
            started.clear()
            refs = _cycles(10 * gc.get_threshold()[0])  # far past the young generation's threshold
            assert started == []  # a decision's allocations start no collection
            assert all(r() is not None for r in refs)
            assert collector.safe_point() == 0  # the young generation was due
            assert started == [0] and collector.collections == [1, 0, 0]
            assert all(r() is None for r in refs)  # the cycles are freed there
            assert collector.safe_point() is None  # nothing due right after
        assert gc.isenabled() == was_enabled and gc.get_freeze_count() == 0
    finally:
        gc.callbacks.remove(seen)


def test_older_generations_are_collected_when_their_thresholds_pass() -> None:
    """As CPython counts: a middle collection once more young ones than its threshold ran, a full one once more
    middle ones than its threshold ran."""
    with SafePointCollector() as collector:
        young, middle, full = gc.get_threshold()
        for _ in range((middle + 2) * (full + 2)):
            _cycles(young + 1)
            collector.safe_point()
        assert collector.collections[1] >= full + 1 and collector.collections[2] >= 1
