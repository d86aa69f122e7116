"""``cvvc schemas``: export the JSON Schema of every bus message."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("schemas", help="message schemas of the bus")
    ssub = p.add_subparsers(dest="schemas_verb", metavar="SUBVERB")
    e = ssub.add_parser("export", help="write one JSON Schema per message type into DIR")
    e.add_argument("dir", metavar="DIR")
    e.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    from schemas.jsonschema import export_schemas

    paths = export_schemas(args.dir)
    for path in paths:
        print(path)
    return 0
