"""``cvvc schemas``: export the JSON Schema of every bus message; ``cvvc security init``: the security profile."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``schemas`` and ``security`` verbs to the ``cvvc`` command line."""
    p = sub.add_parser("schemas", help="message schemas of the bus")
    ssub = p.add_subparsers(dest="schemas_verb", metavar="SUBVERB")
    e = ssub.add_parser("export", help="write one JSON Schema per message type into DIR")
    e.add_argument("dir", metavar="DIR")
    e.set_defaults(func=_export)
    s = sub.add_parser("security", help="security profile: local CA and role certificates (mTLS + access control)")
    ssec = s.add_subparsers(dest="security_verb", metavar="SUBVERB")
    a = ssec.add_parser("init-ca", help="create the local certificate authority in DIR (idempotent); keep DIR "
                        "apart from any run's cache")
    a.add_argument("--dir", required=True, metavar="DIR", help="the CA directory")
    a.set_defaults(func=_security_init_ca)
    i = ssec.add_parser("init", help="issue one certificate per role into DIR from the CA in --ca-dir (idempotent)")
    i.add_argument("--dir", required=True, metavar="DIR", help="the security state directory")
    i.add_argument("--ca-dir", required=True, metavar="CA", help="the CA directory (`cvvc security init-ca`)")
    i.add_argument("--san", action="append", default=[], metavar="HOST_OR_IP",
                   help="also valid for this host name or IP address (repeatable; for use across hosts)")
    i.set_defaults(func=_security_init)
    c = ssec.add_parser("zenoh-config", help="print the Zenoh JSON config of a role (e.g. for zenohd -c)")
    c.add_argument("--dir", required=True, metavar="DIR", help="the security state directory")
    c.add_argument("--role", required=True, choices=["agent", "devices", "recorder", "router"])
    c.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="listen endpoint, e.g. tls/192.0.2.10:7447 (repeatable; routers)")
    c.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="router endpoint to connect to, e.g. tls/192.0.2.10:7447 (repeatable)")
    c.set_defaults(func=_security_zenoh_config)


def _export(args: argparse.Namespace) -> int:
    from schemas.jsonschema import export_schemas

    paths = export_schemas(args.dir)
    for path in paths:
        print(path)
    return 0


def _security_init_ca(args: argparse.Namespace) -> int:
    from schemas.security import init_ca

    written = init_ca(args.dir)
    for path in written:
        print(path)
    print(f"{args.dir}: certificate authority ({'created' if written else 'already there, kept'})")
    return 0


def _security_init(args: argparse.Namespace) -> int:
    from schemas.security import ROLES, init_security_dir

    written = init_security_dir(args.dir, ca_dir=args.ca_dir, extra_sans=tuple(args.san))
    for path in written:
        print(path)
    print(f"{args.dir}: certificates of {', '.join(ROLES)} issued by the CA in {args.ca_dir} "
          f"({'created' if written else 'already there, kept'})")
    return 0


def _security_zenoh_config(args: argparse.Namespace) -> int:
    import json

    from schemas.security import nested_zenoh_config, zenoh_security_settings

    settings = {
        "mode": "router" if args.role == "router" else "client",
        "listen/endpoints": list(args.listen),
        "connect/endpoints": list(args.connect),
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        **zenoh_security_settings(args.dir, args.role),
    }
    print(json.dumps(nested_zenoh_config(settings), indent=2))
    return 0
