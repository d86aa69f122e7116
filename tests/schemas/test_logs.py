"""Rate-limited logging: one line per kind per period, the rest counted and reported on the next line."""

from __future__ import annotations

import logging

from schemas.logs import RateLimitedLog


def test_one_line_per_kind_per_period_and_the_suppressed_are_counted(caplog):
    now = [0.0]
    rlog = RateLimitedLog(logging.getLogger("t"), period_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="t"):
        written = [rlog.warning("flood", "bad %d", i) for i in range(1000)]
        assert rlog.info("other", "another kind") is True  # kinds are limited apart
        now[0] = 10.0
        assert rlog.warning("flood", "bad again") is True
    assert written.count(True) == 1
    assert rlog.suppressed == {"flood": 999}
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["bad 0", "another kind", "bad again (999 more like this in the last 10 s not logged)"]
