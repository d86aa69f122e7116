"""Command-line options that several ``cvvc`` verbs share (``run``, ``evaluate``): argument parsing only."""

from __future__ import annotations

import argparse

__all__ = ["add_agent_option_arguments"]


def add_agent_option_arguments(p: argparse.ArgumentParser) -> None:
    """The agent's options beyond the paper, as ``cvvc run`` and ``cvvc evaluate`` pass them on (docs/agent.md)."""
    p.add_argument("--pv-margin-window-s", type=float, default=None,
                   help="the agent's PV variability margin window [s] (cases A-D; default: the agent's, 1800; "
                        "0 = the paper's method)")
    p.add_argument("--setpoint-hold", action="store_true",
                   help="the agent re-sends its last set point when no tap change is decided (cases C/D)")
    p.add_argument("--control-banks", action="store_true",
                   help="the agent decides and commands the capacitor banks (cases B-D; default: they stay on "
                        "their local control)")
