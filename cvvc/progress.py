"""Progress bars of the long steps (``cvvc run``'s simulation and baseline, ``cvvc evaluate``'s runs): tqdm on
stderr with the rate and the time left, drawn only when stderr is a terminal and not with ``--quiet`` (or
``--json``).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

__all__ = ["QUIET_HELP", "progress_bar", "progress_wanted"]

QUIET_HELP = "no progress bars on stderr (they are off anyway when stderr is not a terminal)"


def progress_wanted(args: argparse.Namespace) -> bool:
    """False with ``--quiet`` or ``--json`` (a machine reads the output), else True."""
    return not (getattr(args, "quiet", False) or getattr(args, "json", False))


def progress_bar(total: float, *, enabled: bool = True, desc: str = "", unit: str = "it") -> Any:
    """A tqdm bar on stderr with elapsed time, rate and time left; disabled (it draws nothing, its methods still work)
    when ``enabled`` is False or stderr is not a terminal.
    """
    from tqdm import tqdm

    try:  # a terminal that says it has no size (a pseudo-terminal nobody sized): 100 x 24, else tqdm draws nothing
        size = os.get_terminal_size(sys.stderr.fileno())
        sized = size.columns > 0 and size.lines > 0
    except (OSError, ValueError):
        sized = False
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=sized,
                ncols=None if sized else 100, nrows=None if sized else 24,
                disable=not (enabled and sys.stderr.isatty()))
