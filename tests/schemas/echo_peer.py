"""A second process for the bus test: echoes every accepted PvCommand back, then reports its counts.

Run: python echo_peer.py ENDPOINT N  -- exits after echoing N good messages (or after 20 s).
"""

from __future__ import annotations

import sys
import time

from schemas import messages as m
from schemas.bus import BusConfig, Inbox, TypedPublisher, open_session
from schemas.examples import example


def main(endpoint: str, n_good: int) -> int:
    with open_session(BusConfig(mode="peer", connect=(endpoint,))) as session:
        inbox = Inbox(maxsize=64)
        inbox.subscribe(session, "test/in", m.PvCommand)
        echo = TypedPublisher(session, "test/out", m.PvCommand, reliable=True)
        report = TypedPublisher(session, "test/report", m.AgentStatus, reliable=True)
        ready = TypedPublisher(session, "test/ready", m.AgentStatus, reliable=True)
        deadline = time.monotonic() + 20.0
        if not echo.wait_matched(10.0):
            return 3
        ready.put(example(m.AgentStatus))
        got = 0
        while got < n_good and time.monotonic() < deadline:
            item = inbox.get(timeout_s=0.2)
            if item is None:
                ready.put(example(m.AgentStatus))  # keep announcing until the first message arrives
                continue
            echo.put(item.msg)
            got += 1
        status = m.AgentStatus(t_ns=1, seq=got, source="peer", feeder_id="test", state="ok",
                               rejected=inbox.rejects.by_kind())
        report.put(status)
        report.wait_matched(1.0)
    return 0 if got == n_good else 4


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2])))
