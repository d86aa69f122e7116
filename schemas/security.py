"""The security profile of the bus: a local CA, one certificate per role, mTLS and the router's access policy.

Two steps, two folders (the CA's private key never sits beside the keys a run uses):

1. ``init_ca(CA)`` (``cvvc security init-ca --dir CA``), once, on the machine that keeps the authority::

       CA/ca.pem, CA/ca.key                the local certificate authority (EC P-256, 10 years)

2. ``init_security_dir(DIR, ca_dir=CA)`` (``cvvc security init --dir DIR --ca-dir CA``) issues from it::

       DIR/ca.pem                          the CA's certificate only (to verify peers)
       DIR/<role>.pem, DIR/<role>.key      one certificate per role, CN = role name,
                                           SAN 127.0.0.1 / localhost, server + client use

for the roles ``agent``, ``devices`` (the bridge: head meter, PV plants, regulators), ``recorder`` and
``router`` (the launcher). ``ensure_local_security`` does both steps when needed: it is every program's default
(secure unless ``--insecure``), with ``<cache>/ca`` and ``<cache>/security``. Private keys are 0600. Running either
again keeps what is there (idempotent); a ``DIR`` that holds a CA key (made by an older version) is refused until
that key is moved out. Rotation:
delete a role's two files in ``DIR`` and run step 2 again (docs/security.md).

``zenoh_security_settings(DIR, role)`` gives the Zenoh config entries of a role: TLS certificate and key for
both listening and connecting, the CA, ``enable_mtls`` and, for the router, an ``access_control`` policy with
``default_permission: deny`` whose subjects are the common names of the peers' certificates. Zenoh applies
the policy on the router, per link, by the certificate of the session at the other end of that link; the
other programs join as clients (they never listen), so every message crosses the router and its policy.
See ``docs/security.md``.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from pathlib import Path
from typing import Any, Literal

from schemas.errors import CvvcError

__all__ = [
    "COMMAND_ROLE",
    "INSECURE_WARNING",
    "ROLES",
    "SecurityError",
    "SecurityRole",
    "access_control_policy",
    "feeder_common_name",
    "ensure_local_security",
    "init_ca",
    "init_security_dir",
    "nested_zenoh_config",
    "role_paths",
    "zenoh_security_settings",
]

SecurityRole = Literal["agent", "devices", "recorder", "router"]
ROLES: tuple[SecurityRole, ...] = ("agent", "devices", "recorder", "router")
COMMAND_ROLE: SecurityRole = "agent"
"""The one certificate (common name) the access policy lets publish commands (``cvvc/*/cmd/**``): in secure mode
the devices key their replay protection on it rather than on the ``source`` a command names itself."""
INSECURE_WARNING = ("--insecure: the bus runs without TLS and without access control; any process that reaches its "
                    "port reads every frame and may command every device (docs/security.md)")
"""What every program says (stderr) when it runs with ``--insecure``; the run's summary records it too."""
_CA_DAYS = 3650
_CERT_DAYS = 825
_ROOT = "cvvc"


class SecurityError(CvvcError):
    """A security state directory that cannot be created or used."""


# ---------------------------------------------------------------------------------- certificates
def role_paths(state_dir: str | Path, role: str) -> tuple[Path, Path]:
    """(certificate, private key) paths of ``role`` in ``state_dir``; ``role`` may also be ``"ca"``."""
    d = Path(state_dir)
    return d / f"{role}.pem", d / f"{role}.key"


def _private_dir(d: Path, what: str) -> None:
    try:
        d.mkdir(parents=True, exist_ok=True)
        os.chmod(d, 0o700)
    except OSError as e:
        raise SecurityError(f"cannot create the {what} {d}: {e}") from e


def init_ca(ca_dir: str | Path) -> list[Path]:
    """Create the local certificate authority in ``ca_dir`` unless it exists; returns the files written.

    Keep ``ca_dir`` apart from any run's cache (its key signs every certificate of the bus).
    """
    d = Path(ca_dir)
    _private_dir(d, "CA directory")
    cert_path, key_path = role_paths(d, "ca")
    if cert_path.is_file() and key_path.is_file():
        _load(cert_path, key_path)  # readable, or a clear error
        return []
    cert, key = _make_ca()
    return _write(cert_path, key_path, cert, key)


def feeder_common_name(role: str, feeder: str) -> str:
    """The common name of one feeder's ``agent`` or ``devices`` certificate in a fleet (``cvvc fleet --secure``):
    ``<role>.<feeder>``, a subject of the router's policy allowed only on that feeder's keys.
    """
    return f"{role}.{feeder}"


def init_security_dir(state_dir: str | Path, *, ca_dir: str | Path, extra_sans: tuple[str, ...] = (),
                      feeder: str | None = None) -> list[Path]:
    """Issue every role's certificate into ``state_dir`` from the CA in ``ca_dir``; returns the files written.

    With ``feeder`` (a fleet, one such directory per feeder): only the ``agent`` and ``devices`` certificates,
    with the common names ``feeder_common_name(role, feeder)``, so the router's policy (``access_control_policy``
    with ``feeders``) lets them on that feeder's keys alone; the programs still load ``agent.pem`` / ``devices.pem``.

    ``state_dir`` gets the CA's certificate, never its key. Idempotent: existing role certificates are kept
    (delete a role's two files to reissue it), unless another CA issued them: they are then issued again.
    Private keys are written 0600, the directory is 0700. ``extra_sans`` (host names or IP addresses) are added to
    the subject alternative names of new certificates, beside 127.0.0.1 and localhost, for use across hosts.

    Raises
    ------
    SecurityError
        No CA in ``ca_dir`` (run ``cvvc security init-ca`` first), or ``state_dir`` holds a CA key.
    """
    d = Path(state_dir)
    ca_cert_path, ca_key_path = role_paths(ca_dir, "ca")
    if not (ca_cert_path.is_file() and ca_key_path.is_file()):
        raise SecurityError(f"no certificate authority in {ca_dir}; create one with `cvvc security init-ca "
                            f"--dir {ca_dir}` (keep it apart from the run's cache)")
    stray_key = role_paths(d, "ca")[1]
    if stray_key.exists() and Path(ca_dir).resolve() != d.resolve():
        raise SecurityError(f"{stray_key} is a CA private key inside a run's security directory; move it out "
                            "(e.g. into the folder you pass as --ca-dir) and run again")
    ca_cert, ca_key = _load(ca_cert_path, ca_key_path)
    _private_dir(d, "security directory")
    written: list[Path] = []
    state_ca = role_paths(d, "ca")[0]
    if not state_ca.is_file() or state_ca.read_bytes() != ca_cert_path.read_bytes():
        if state_ca.is_file():  # another CA issued what is here: its certificates would fail every handshake
            for role in ROLES:
                for path in role_paths(d, role):
                    path.unlink(missing_ok=True)
        try:
            state_ca.write_bytes(ca_cert_path.read_bytes())
        except OSError as e:
            raise SecurityError(f"cannot write {state_ca}: {e}") from e
        written.append(state_ca)
    for role in ROLES if feeder is None else ("agent", "devices"):
        cert_path, key_path = role_paths(d, role)
        if cert_path.is_file() and key_path.is_file():
            continue
        name = role if feeder is None else feeder_common_name(role, feeder)
        cert, key = _make_leaf(name, ca_cert, ca_key, extra_sans)
        written += _write(cert_path, key_path, cert, key)
    return written


def ensure_local_security(state_dir: str | Path, *, ca_dir: str | Path) -> list[Path]:
    """The default of every program (secure unless ``--insecure``): create the CA in ``ca_dir`` when there is
    none (the first run, no question asked), then issue every role's certificate into ``state_dir``
    (``init_security_dir``). ``ca_dir`` must not be ``state_dir``: the CA's key never sits beside the role keys.
    Returns the files written (none once both exist).
    """
    if Path(ca_dir).resolve() == Path(state_dir).resolve():
        raise SecurityError(f"the CA folder {ca_dir} is the role certificates' folder; give the CA a folder of its "
                            "own (its key must not sit beside the keys a run uses)")
    import fcntl

    lock_path = Path(state_dir).resolve().parent / ".security.lock"  # runs started side by side make one CA
    try:
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        lock = open(lock_path, "a")  # noqa: SIM115  (closed below)
    except OSError as e:
        raise SecurityError(f"cannot create {lock_path}: {e}") from e
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return init_ca(ca_dir) + init_security_dir(state_dir, ca_dir=ca_dir)


def _make_ca():
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cvvc-edge"),
                      x509.NameAttribute(NameOID.COMMON_NAME, "cvvc-edge local CA")])
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder()
            .subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=_CA_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return cert, key


def _make_leaf(role: str, ca_cert, ca_key, extra_sans: tuple[str, ...] = ()):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    names: list[x509.GeneralName] = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.IPv4Address("127.0.0.1"))]
    for name in extra_sans:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            names.append(x509.DNSName(name))
    san = x509.SubjectAlternativeName(names)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cvvc-edge"),
                                     x509.NameAttribute(NameOID.COMMON_NAME, role)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=_CERT_DAYS))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(san, critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    return cert, key


def _write(cert_path: Path, key_path: Path, cert, key) -> list[Path]:
    from cryptography.hazmat.primitives import serialization

    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    try:
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(key_pem)
        os.chmod(key_path, 0o600)
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    except OSError as e:
        raise SecurityError(f"cannot write {cert_path} / {key_path}: {e}") from e
    return [cert_path, key_path]


def _load(cert_path: Path, key_path: Path):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError) as e:
        raise SecurityError(f"cannot read the CA in {cert_path.parent}: {e}; remove the directory and run "
                            "`cvvc security init-ca` again") from e
    return cert, key


# ---------------------------------------------------------------------------------- zenoh settings
def zenoh_security_settings(state_dir: str | Path, role: str, feeders: tuple[str, ...] = (), *,
                            policy: bool | None = None) -> dict[str, Any]:
    """Zenoh config entries (path -> value) for ``role``: mTLS with the role's certificate, and for the
    router the access-control policy (with the per-feeder subjects of ``feeders``, a fleet). ``policy``: whether
    to add the policy (default: for the ``router`` role); any session in router mode needs it, e.g. a bridge that
    only listens, else its clients would be allowed everything. Raises ``SecurityError`` if the files are missing.
    """
    if role not in ROLES:
        raise SecurityError(f"unknown security role {role!r}; use one of {', '.join(ROLES)}")
    ca, _ = role_paths(state_dir, "ca")
    cert, key = role_paths(state_dir, role)
    missing = [str(p) for p in (ca, cert, key) if not p.is_file()]
    if missing:
        raise SecurityError(f"missing {', '.join(missing)}; run `cvvc security init --dir {state_dir} --ca-dir CA` "
                            "first")
    tls = "transport/link/tls"
    out: dict[str, Any] = {
        "transport/link/protocols": ["tls"],
        f"{tls}/root_ca_certificate": str(ca.resolve()),
        f"{tls}/listen_certificate": str(cert.resolve()),
        f"{tls}/listen_private_key": str(key.resolve()),
        f"{tls}/connect_certificate": str(cert.resolve()),
        f"{tls}/connect_private_key": str(key.resolve()),
        f"{tls}/enable_mtls": True,
        f"{tls}/verify_name_on_connect": True,
    }
    if role == "router" if policy is None else policy:
        out["access_control"] = access_control_policy(feeders)
    return out


_ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")


def _rule(rule_id: str, messages: tuple[str, ...] | list[str], flows: list[str], key_exprs: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "messages": list(messages), "flows": flows,
            "key_exprs": key_exprs}


def access_control_policy(feeders: tuple[str, ...] = ()) -> dict[str, Any]:
    """The router's ``access_control`` section: deny by default; subjects by certificate common name.

    Flows are seen from the router: ``ingress`` is what a role sends to the router, ``egress`` what the
    router forwards to that role. A message reaches its destination only if the sender's ingress *and*
    the receiver's egress are allowed. The rules of the subjects ``agent`` and ``devices`` are written for all
    feeders (``cvvc/*/...``); for each id of ``feeders`` (a fleet) the subjects ``agent.<id>`` and
    ``devices.<id>`` (``feeder_common_name``) get the same rules on ``cvvc/<id>/...`` only, so one feeder's
    agent can neither command another feeder's devices nor read its frames.
    """
    r = _ROOT
    # what the bridge and the head-clocked adapters read of the devices behind a field protocol: frames and acks
    adapted = [f"{r}/*/{group}/{kind}/*" for kind in ("pv", "vr", "cap") for group in ("meas", "ack")]
    alive = f"{r}/*/alive/**"
    rules = [
        # agent: commands, decisions and status out; frames and acks in; the oracle (case A). The only role that
        # may put on cmd/** (COMMAND_ROLE: the devices' replay protection is keyed on it in secure mode)
        _rule("agent-send", ["put"], ["ingress"],
              [f"{r}/*/cmd/**", f"{r}/*/agent/decision", f"{r}/*/agent/status"]),
        _rule("agent-subscribe", ["declare_subscriber"], ["ingress"],
              [f"{r}/*/meas/**", f"{r}/*/ack/**"]),
        _rule("agent-receive", ["put"], ["egress"], [f"{r}/*/meas/**", f"{r}/*/ack/**"]),
        _rule("agent-oracle", ["query"], ["ingress"], [f"{r}/*/sim/oracle"]),
        _rule("agent-oracle-reply", ["reply"], ["egress"], [f"{r}/*/sim/oracle"]),
        _rule("agent-alive", ["liveliness_token"], ["ingress"], [f"{r}/*/alive/agent/*"]),
        _rule("agent-alive-watch", ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"], [alive]),
        _rule("agent-alive-see", ["liveliness_token"], ["egress"], [alive]),
        # devices (the bridge, protocol adapters): frames, acks, link states, simulation frames and oracle replies
        # out; commands in
        _rule("devices-send", ["put"], ["ingress"],
              [f"{r}/*/meas/**", f"{r}/*/ack/**", f"{r}/*/link/**", f"{r}/*/sim/**"]),
        # ... and, for SunSpec and DNP3 adapters clocked on the head (``--clock head``) and the bridge that waits for
        # their frames, the head frame, the device frames and acks (what a devices certificate may send anyway)
        _rule("devices-subscribe", ["declare_subscriber"], ["ingress"], [f"{r}/*/cmd/**", f"{r}/*/agent/decision",
              f"{r}/*/meas/head", *adapted]),
        _rule("devices-receive", ["put"], ["egress"], [f"{r}/*/cmd/**", f"{r}/*/agent/decision",
              f"{r}/*/meas/head", *adapted]),
        _rule("devices-oracle", ["declare_queryable", "reply"], ["ingress"], [f"{r}/*/sim/oracle"]),
        _rule("devices-oracle-query", ["query"], ["egress"], [f"{r}/*/sim/oracle"]),
        _rule("devices-alive", ["liveliness_token"], ["ingress"],
              [f"{r}/*/alive/bridge/*", f"{r}/*/alive/head/*", f"{r}/*/alive/pv/*", f"{r}/*/alive/vr/*",
               f"{r}/*/alive/cap/*"]),  # cap: a bank's DNP3 adapter (cvvc adapter dnp3 --kind cap)
        _rule("devices-alive-watch", ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"], [alive]),
        _rule("devices-alive-see", ["liveliness_token"], ["egress"], [alive]),
        # recorder: subscribe to everything, send nothing
        _rule("recorder-subscribe", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
              ["ingress"], [f"{r}/**"]),
        _rule("recorder-receive", ["put", "liveliness_token"], ["egress"], [f"{r}/**"]),
        _rule("recorder-alive", ["liveliness_token"], ["ingress"], [f"{r}/*/alive/recorder/*"]),
        # every role's subscriptions and queryables are declared to the others (the router forwards them)
        _rule("declarations-to-senders", ["declare_subscriber", "declare_queryable"], ["egress"], [f"{r}/**"]),
    ]
    subjects = [{"id": role, "cert_common_names": [role]} for role in ("agent", "devices", "recorder")]
    policies = [
        {"id": "agent", "subjects": ["agent"], "rules": [x["id"] for x in rules if x["id"].startswith("agent")]},
        {"id": "devices", "subjects": ["devices"],
         "rules": [x["id"] for x in rules if x["id"].startswith("devices")]},
        {"id": "recorder", "subjects": ["recorder"],
         "rules": [x["id"] for x in rules if x["id"].startswith("recorder")]},
        {"id": "declarations", "subjects": ["agent", "devices", "recorder"], "rules": ["declarations-to-senders"]},
    ]
    base, names = list(rules), []
    for f in feeders:  # a fleet: each feeder's agent and devices on that feeder's keys alone
        for role in ("agent", "devices"):
            scoped = [_feeder_rule(x, f) for x in base if x["id"].startswith(f"{role}-")]
            name = feeder_common_name(role, f)
            subjects.append({"id": name, "cert_common_names": [name]})
            policies.append({"id": name, "subjects": [name], "rules": [x["id"] for x in scoped]})
            rules += scoped
            names.append(name)
    i = next(i for i, x in enumerate(policies) if x["id"] == "declarations")
    policies[i] = {**policies[i], "subjects": ["agent", "devices", "recorder", *names]}
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _feeder_rule(rule: dict[str, Any], feeder: str) -> dict[str, Any]:
    """``rule`` on one feeder's keys: ``cvvc/*/...`` becomes ``cvvc/<feeder>/...``, under a rule id of its own.

    Rules that only declare interest (subscriptions, liveliness subscriptions and queries) keep every feeder's
    keys: the bridge subscribes to ``cvvc/*/cmd/**`` (to answer a command sent to a feeder that has no bridge),
    and what reaches a subscriber is decided by the egress rules, which are scoped.
    """
    if set(rule["messages"]) <= _INTEREST_ONLY:
        return {**rule, "id": f"{feeder_common_name(rule['id'].split('-')[0], feeder)}-{rule['id']}"}
    prefix = f"{_ROOT}/*/"
    exprs = [f"{_ROOT}/{feeder}/{k[len(prefix):]}" if k.startswith(prefix) else k for k in rule["key_exprs"]]
    return {**rule, "id": f"{feeder_common_name(rule['id'].split('-')[0], feeder)}-{rule['id']}", "key_exprs": exprs}


_INTEREST_ONLY = frozenset({"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"})


def nested_zenoh_config(settings: dict[str, Any]) -> dict[str, Any]:
    """Turn ``{"a/b/c": v}`` entries into nested JSON (``{"a": {"b": {"c": v}}}``), e.g. for ``zenohd -c``."""
    out: dict[str, Any] = {}
    for path, value in settings.items():
        node = out
        *parents, leaf = path.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out
