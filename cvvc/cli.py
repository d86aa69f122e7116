"""The ``cvvc`` command: a thin dispatcher over the verbs each package registers.

Each package that offers verbs has a ``cli.py`` with ``register(subparsers)``. A verb's parser sets
``func=handler`` where ``handler(args) -> int`` is the exit status. ``cli.py`` modules import nothing heavy
at module level (no OpenDSS, no Zenoh), so ``cvvc --help`` stays fast; handlers import what they need.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cvvc.errors import CliError
from cvvc.parent_watch import watch_parent
from schemas.errors import CvvcError
from schemas.version import __version__

__all__ = ["main", "build_parser", "CliError"]

# Packages whose ``cli.register`` adds verbs, in the order they appear in ``--help``.
_VERB_MODULES = (
    "schemas.cli",
    "simulator_bridge.bus.cli",
    "cvvc.advise_cli",  # a sub-verb of `feeder`: after it
    "training.cli",
    "agent.cli",
    "recordings.cli",
    "adapters.cli",
    "cvvc.launch_cli",
    "cvvc.fleet_cli",
)


def build_parser() -> argparse.ArgumentParser:
    """The ``cvvc`` parser: global flags and every package's verbs (each ``<package>.cli.register``)."""
    parser = argparse.ArgumentParser(
        prog="cvvc",
        description="cvvc-edge: regression-based centralized volt-var control over Eclipse Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"cvvc-edge {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for name in _VERB_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name == name:  # that package has no verbs yet
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the verb of ``argv`` (default: ``sys.argv[1:]``); returns the exit status (2: a ``CvvcError``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    watch_parent()  # a child of `cvvc run` ends with it (cvvc.parent_watch)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.verb is None else 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` and closed: not an error of ours
        sys.stderr.close()
        return 0
    except CvvcError as e:  # every project error: one line, exit status 2, never a traceback
        print(f"cvvc {_verb_path(args)}: error: {e}", file=sys.stderr)
        return 2


def _verb_path(args: argparse.Namespace) -> str:
    """``feeder info``, ``recordings recover``...: the verb and the sub-verb the user typed."""
    subs = [v for k, v in sorted(vars(args).items()) if k.endswith("_verb") and isinstance(v, str)]
    return " ".join([args.verb, *subs])


if __name__ == "__main__":
    sys.exit(main())
