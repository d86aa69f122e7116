"""CPython's cyclic garbage collector kept out of the agent's decisions.

The collector runs when a generation's allocation count passes its threshold, in whichever thread allocates (a
Zenoh callback's included), and holds the interpreter while it walks every tracked object of the generations it
collects. In the agent that walk lands inside decisions: re-running a recorded IEEE 123 summer day's 864 decisions
offline (frames read one at a time, as live) took 253 young collections of up to 6.9 ms, 23 middle ones of up to
6.0 ms and 2 full ones of 119 and 135 ms; every module, the model and the solvers' bindings are tracked objects,
so a full collection is long.

In the agent's own process (``run_agent(..., own_process=True)``, ``python -m agent``), :class:`SafePointCollector`
freezes what is alive once the model is loaded (``gc.freeze``: modules, the model; never collected again), turns
the automatic collector off, and runs the collection that would have been due at safe points the runtime chooses:
between steps, once a step's decision is out and before the next step's first frame, never inside a decision. The thresholds are CPython's (a generation is
collected once the count of collections of the one below passes its threshold), without its rule that defers a full
collection until the objects awaiting one are a quarter of the long-lived ones. With the start frozen, the full
collections of the same day took 33 and 57 ms. An agent run in a thread of another process (tests, the API) leaves
the process's collector alone.
"""

from __future__ import annotations

import gc
from types import TracebackType

__all__ = ["SafePointCollector"]


class SafePointCollector:
    """A context in which the cyclic collector runs only at :meth:`safe_point` (see the module docstring).

    ``collections[g]``: the collections of generation ``g`` run at safe points.
    """

    def __init__(self) -> None:
        self.collections = [0, 0, 0]
        self._was_enabled = False

    def __enter__(self) -> SafePointCollector:
        gc.collect()
        gc.freeze()
        self._was_enabled = gc.isenabled()
        gc.disable()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()

    def safe_point(self) -> int | None:
        """Run the collection due now, if any (the oldest generation whose count passed its threshold); its
        generation, or None.
        """
        counts, thresholds = gc.get_count(), gc.get_threshold()
        due = next((g for g in (2, 1, 0) if thresholds[g] and counts[g] > thresholds[g]), None)
        if due is not None:
            gc.collect(due)
            self.collections[due] += 1
        return due
