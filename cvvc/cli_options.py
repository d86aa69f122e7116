"""Command-line options that several ``cvvc`` verbs share (``run``, ``evaluate``, ``fleet``): argument parsing only."""

from __future__ import annotations

import argparse

from schemas.settings import AgentOptions

__all__ = ["add_agent_option_arguments", "add_security_arguments"]

_AGENT = AgentOptions()  # the defaults the help texts name


def add_agent_option_arguments(p: argparse.ArgumentParser) -> None:
    """The agent's options beyond the paper, as ``cvvc run`` and ``cvvc evaluate`` pass them on (docs/agent.md);
    each None when not given (``cvvc.case.agent_options_from_args`` lays the given ones over the settings tree).
    """
    p.add_argument("--pv-margin-window-s", type=float, default=None,
                   help=f"the agent's PV variability margin window [s] (cases A-D; default "
                        f"{_AGENT.pv_margin_window_s:g}; 0 = the paper's method)")
    p.add_argument("--setpoint-hold", action="store_const", const=True, default=None,
                   help="the agent re-sends its last set point when no tap change is decided (cases C/D)")
    p.add_argument("--control-banks", action="store_const", const=True, default=None,
                   help="the agent decides and commands the capacitor banks (cases B-D; default: they stay on "
                        "their local control)")


def add_security_arguments(p: argparse.ArgumentParser) -> None:
    """``--insecure``, ``--ca-dir`` and the no-op ``--secure`` of the launchers (``run``, ``fleet``, ``evaluate``)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--insecure", action="store_true",
                   help="run the bus without TLS and access control (prints a warning; recorded in the summary). "
                        "Default: mTLS with per-role certificates in <cache>/security and the router's "
                        "deny-by-default access policy; see docs/security.md")
    g.add_argument("--secure", action="store_true", help="the default (kept for earlier command lines)")
    p.add_argument("--ca-dir", metavar="CA", help="the certificate authority that issues the certificates "
                   "(default <cache>/ca, created on the first run; or one made with `cvvc security init-ca`)")
