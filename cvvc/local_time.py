"""The profiles' clock: fixed local standard time, UTC-5 without daylight saving (docs/conventions.md).

Simulation times are nanoseconds since the UTC epoch everywhere; what a user reads (reports, ``--at``) is this
local time.
"""

from __future__ import annotations

import numpy as np

from simulator_bridge.rural.synthesis import UTC_OFFSET_H

__all__ = ["LOCAL_UTC_OFFSET_NS", "local_minute"]

LOCAL_UTC_OFFSET_NS = UTC_OFFSET_H * 3_600_000_000_000
"""Local standard time minus UTC [ns]."""


def local_minute(t_ns: int) -> str:
    """A simulation time [ns since the UTC epoch] as the profiles' local standard time, ``YYYY-MM-DD HH:MM``."""
    return str(np.datetime64(int(t_ns) + LOCAL_UTC_OFFSET_NS, "ns").astype("datetime64[m]")).replace("T", " ")
