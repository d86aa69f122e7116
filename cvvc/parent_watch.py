"""A process ``cvvc run`` starts (bridge, agent, recorder, adapters) ends when its launcher is gone.

``cvvc run`` stops its children by their ids when it ends, fails or is interrupted. A launcher killed outright
(SIGKILL: a test's or a batch system's timeout) cannot, and its children would go on, holding ports and files. So the
launcher hands each child its own process id (``PARENT_ENV``), and the child, through :func:`watch_parent`, checks
every second whether it is still that process's child; once re-parented it sends itself SIGTERM, on which every
child ends cleanly (its session closed, a recording finished). The variable is taken out of the child's environment,
so that a process the child starts does not take the child's launcher for its own.
"""

from __future__ import annotations

import os
import signal
import threading
import time

__all__ = ["PARENT_ENV", "watch_parent"]

PARENT_ENV = "CVVC_PARENT_PID"
"""The launcher's process id, set in a child's environment by ``cvvc run``."""


def watch_parent(period_s: float = 1.0) -> threading.Thread | None:
    """Watch the launcher named by ``PARENT_ENV`` (and remove the variable); None when none was named."""
    value = os.environ.pop(PARENT_ENV, None)
    if not value:
        return None
    parent = int(value)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        os.kill(os.getpid(), signal.SIGTERM)  # re-parented: the launcher is gone

    thread = threading.Thread(target=watch, name="parent-watch", daemon=True)
    thread.start()
    return thread
