"""``cvvc schemas``: export the JSON Schema of every bus message; ``cvvc security init``: the security profile."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("schemas", help="message schemas of the bus")
    ssub = p.add_subparsers(dest="schemas_verb", metavar="SUBVERB")
    e = ssub.add_parser("export", help="write one JSON Schema per message type into DIR")
    e.add_argument("dir", metavar="DIR")
    e.set_defaults(func=_export)
    s = sub.add_parser("security", help="security profile: local CA and role certificates (mTLS + access control)")
    ssec = s.add_subparsers(dest="security_verb", metavar="SUBVERB")
    i = ssec.add_parser("init", help="create a local CA and one certificate per role in DIR (idempotent)")
    i.add_argument("--dir", required=True, metavar="DIR", help="the security state directory")
    i.set_defaults(func=_security_init)


def _export(args: argparse.Namespace) -> int:
    from schemas.jsonschema import export_schemas

    paths = export_schemas(args.dir)
    for path in paths:
        print(path)
    return 0


def _security_init(args: argparse.Namespace) -> int:
    from schemas.security import ROLES, init_security_dir

    written = init_security_dir(args.dir)
    for path in written:
        print(path)
    print(f"{args.dir}: CA and certificates of {', '.join(ROLES)} "
          f"({'created' if written else 'already there, kept'})")
    return 0
