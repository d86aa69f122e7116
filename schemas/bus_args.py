"""The Zenoh flags every program takes (``--listen``, ``--connect``, ``--zenoh-config``, ``--zenoh-mode``,
``--secure-dir``, ``--insecure``): argument parsing only, so a command line is checked before Zenoh or NumPy load
(``schemas.bus.bus_config_from_args`` turns the parsed flags into a ``BusConfig``).
"""

from __future__ import annotations

import argparse

__all__ = ["add_bus_arguments"]


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags every program takes, the same way everywhere."""
    g = parser.add_argument_group("bus (Zenoh)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="listen on this endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="connect to this endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE", default=None,
                   help="a Zenoh JSON5 config file (multicast scouting is still forced off)")
    g.add_argument("--zenoh-mode", choices=["peer", "router", "client"], default=None,
                   help="session mode (default: peer, or router when only listening)")
    sec = g.add_mutually_exclusive_group()
    sec.add_argument("--secure-dir", metavar="DIR", default=None,
                     help="mTLS with this program's certificate from DIR (made by `cvvc security init --dir DIR`); "
                          "default: <cache>/security, issued on first use from a local CA made in <cache>/ca; "
                          "tcp/ endpoints become tls/, peers join as clients (docs/security.md)")
    sec.add_argument("--insecure", action="store_true",
                     help="no TLS and no access control: any process that reaches the port may read and command "
                          "(prints a warning)")
