"""The security profile on real Zenoh over loopback: mTLS with role certificates and the router's policy.

One router-mode session per test holds the access-control policy (as ``cvvc run --secure`` does); the
others join as clients with a role's certificate. Every "0 received" is bounded by a positive control on
the same router: a legitimate sender's messages, sent afterwards, must all arrive.
"""

from __future__ import annotations

import contextlib
import shutil
import stat
import threading
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from schemas.bus import BusConfig, BusError, free_port, open_session, wait_for, zenoh_config
from schemas.security import (
    ROLES,
    SecurityError,
    init_ca,
    init_security_dir,
    role_paths,
    zenoh_security_settings,
)

N = 20


@pytest.fixture(scope="module")
def security_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("security")
    ca = tmp_path_factory.mktemp("ca")
    init_ca(ca)
    init_security_dir(d, ca_dir=ca)
    return d


@pytest.fixture(params=["bus", "exported"])
def secure_router(request, security_dir, tmp_path) -> Iterator[str]:
    """A router with the policy on a free port; yields its ``tcp/`` endpoint (clients turn it into ``tls/``).

    ``bus``: opened by ``schemas.bus`` as ``cvvc run --secure`` does; ``exported``: from the JSON file that
    ``cvvc security zenoh-config --role router`` prints (what a separate ``zenohd`` would load).
    """
    port = free_port()
    if request.param == "bus":
        with open_session(BusConfig(mode="router", listen=(f"tcp/127.0.0.1:{port}",), tls_dir=str(security_dir),
                                    role="router")):
            yield f"tcp/127.0.0.1:{port}"
        return
    from cvvc.cli import main

    out = tmp_path / "router.json5"
    with open(out, "w") as f, contextlib.redirect_stdout(f):
        assert main(["security", "zenoh-config", "--dir", str(security_dir), "--role", "router",
                     "--listen", f"tls/127.0.0.1:{port}"]) == 0
    with zenoh.open(zenoh.Config.from_file(str(out))):
        yield f"tcp/127.0.0.1:{port}"


def _client(endpoint: str, state_dir: Path, role: str, *, mode: str = "client", **kw) -> zenoh.Session:
    """A session with ``role``'s certificate; ``mode`` other than client (what an attacker may pick) is
    forced into the config after ``zenoh_config``, which would make a peer a client.
    """
    conf = zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(state_dir), role=role, **kw))
    if mode != "client":
        conf.insert_json5("mode", f'"{mode}"')
        conf.insert_json5("listen/endpoints", '["tls/127.0.0.1:0"]')
    try:
        return zenoh.open(conf)
    except Exception as e:  # zenoh raises ZError, a plain Exception subclass
        raise BusError(str(e)) from e


class _Counter:
    """Counts received samples by (key, payload), thread-safe."""

    def __init__(self) -> None:
        self.counts: Counter[tuple[str, bytes]] = Counter()
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.counts[(str(sample.key_expr), sample.payload.to_bytes())] += 1

    def get(self, key: str, payload: bytes) -> int:
        with self._lock:
            return self.counts[(key, payload)]


# ------------------------------------------------------------------------------------ certificates
def test_init_makes_one_certificate_per_role_signed_by_the_ca_and_is_idempotent(tmp_path):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    d, ca_dir = tmp_path / "sec", tmp_path / "ca"
    with pytest.raises(SecurityError, match="init-ca"):  # no CA yet: the explicit CA step comes first
        init_security_dir(d, ca_dir=ca_dir)
    assert init_ca(ca_dir) == list(role_paths(ca_dir, "ca")) and init_ca(ca_dir) == []
    written = init_security_dir(d, ca_dir=ca_dir)
    assert len(written) == 1 + 2 * len(ROLES)  # the CA's certificate and each role's two files
    assert not role_paths(d, "ca")[1].exists()  # (j): the CA key never sits in the run's directory
    ca = x509.load_pem_x509_certificate(role_paths(d, "ca")[0].read_bytes())
    for role in ROLES:
        cert_path, key_path = role_paths(d, role)
        assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        cert.verify_directly_issued_by(ca)  # raises if not signed by our CA
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert "localhost" in san.get_values_for_type(x509.DNSName)
        assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert stat.S_IMODE(role_paths(ca_dir, "ca")[1].stat().st_mode) == 0o600
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    assert init_security_dir(d, ca_dir=ca_dir) == []  # second run keeps everything
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before
    role_paths(d, "agent")[0].unlink()
    assert init_security_dir(d, ca_dir=ca_dir) == list(role_paths(d, "agent"))  # rotation: a role reissued
    shutil.copy(role_paths(ca_dir, "ca")[1], role_paths(d, "ca")[1])  # an old layout's CA key in the run's dir
    with pytest.raises(SecurityError, match="CA private key"):
        init_security_dir(d, ca_dir=ca_dir)


def test_secure_config_uses_tls_endpoints_mtls_and_clients(security_dir):
    conf = zenoh_config(BusConfig(connect=("tcp/127.0.0.1:7999",), tls_dir=str(security_dir), role="agent"))
    assert conf.get_json("mode") == '"client"'  # a peer would accept direct links past the router's policy
    assert conf.get_json("connect/endpoints") == '["tls/127.0.0.1:7999"]'
    assert conf.get_json("listen/endpoints") == "[]"
    assert conf.get_json("transport/link/tls/enable_mtls") == "true"
    assert conf.get_json("access_control/enabled") == "false"  # only the router holds the policy
    router = zenoh_config(BusConfig(mode="router", listen=("tcp/127.0.0.1:7999",), tls_dir=str(security_dir),
                                    role="router"))
    assert router.get_json("listen/endpoints") == '["tls/127.0.0.1:7999"]'
    assert router.get_json("access_control/enabled") == "true"
    assert router.get_json("access_control/default_permission") == '"deny"'
    with pytest.raises(BusError, match="needs a role"):
        zenoh_config(BusConfig(connect=("tcp/127.0.0.1:7999",), tls_dir=str(security_dir)))
    with pytest.raises(BusError, match="cvvc security init"):
        zenoh_config(BusConfig(connect=("tcp/127.0.0.1:7999",), tls_dir=str(security_dir / "nope"), role="agent"))
    with pytest.raises(SecurityError, match="unknown security role"):
        zenoh_security_settings(security_dir, "admin")


# ------------------------------------------------------------------------------------ authentication
def test_certificate_of_another_ca_cannot_connect(security_dir, secure_router, tmp_path):
    other = tmp_path / "other"
    init_ca(tmp_path / "other-ca")
    init_security_dir(other, ca_dir=tmp_path / "other-ca")
    # trusts the right CA (so it accepts the router) but presents an agent certificate of another CA:
    # only the router's check of the client certificate can refuse it
    rogue = tmp_path / "rogue"
    rogue.mkdir()
    shutil.copy(role_paths(security_dir, "ca")[0], role_paths(rogue, "ca")[0])
    for src in role_paths(other, "agent"):
        shutil.copy(src, rogue / src.name)
    with pytest.raises(BusError, match="Unable to connect"):
        _client(secure_router, rogue, "agent", connect_timeout_ms=1000)
    with pytest.raises(BusError, match="Unable to connect"):  # everything of the other CA
        _client(secure_router, other, "agent", connect_timeout_ms=1000)
    tls_endpoint = secure_router.replace("tcp/", "tls/")
    with pytest.raises(BusError, match="Unable to connect"):  # plain TCP to the TLS port
        open_session(BusConfig(mode="client", connect=(secure_router,), connect_timeout_ms=1000))
    with _client(secure_router, security_dir, "agent", connect_timeout_ms=1000) as ok:  # control: ours does
        assert ok.info.routers_zid(), f"a valid agent certificate should reach the router on {tls_endpoint}"


# ------------------------------------------------------------------------------------ access control
def test_wrong_roles_cannot_command_a_device_or_impersonate_one(security_dir, secure_router):
    cmd_key, meas_key = "cvvc/F/cmd/pv/x", "cvvc/F/meas/pv/x"
    device_seen, agent_seen = _Counter(), _Counter()
    with (_client(secure_router, security_dir, "devices") as device,
          _client(secure_router, security_dir, "agent") as agent):
        device.declare_subscriber("cvvc/*/cmd/**", device_seen)  # the device under attack
        agent.declare_subscriber("cvvc/*/meas/**", agent_seen)  # who must not be fooled by fake frames
        for role, mode in [("recorder", "client"), ("recorder", "peer"), ("recorder", "router"),
                           ("devices", "client"), ("agent", "client"), ("router", "client")]:
            with _client(secure_router, security_dir, role, mode=mode) as attacker:
                for key in (cmd_key, meas_key):
                    if (role, key) in (("agent", cmd_key), ("devices", meas_key)):
                        continue  # their own legitimate flows: the control below
                    pub = attacker.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                    # the router shows it the subscriber (so nothing is lost for want of a route)...
                    if role != "router":
                        assert wait_for(lambda p=pub: bool(p.matching_status.matching), 5.0), (role, key)
                    for _ in range(N):
                        pub.put(f"forged by {role} ({mode})".encode())
        # ... and the legitimate senders, afterwards on the same router, get every message through
        for _ in range(N):
            agent.put(cmd_key, b"agent", congestion_control=zenoh.CongestionControl.BLOCK)
            device.put(meas_key, b"devices", congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(lambda: device_seen.get(cmd_key, b"agent") == N
                        and agent_seen.get(meas_key, b"devices") == N, 10.0)
        forged_cmds = {k: n for k, n in device_seen.counts.items() if k[1] != b"agent"}
        forged_frames = {k: n for k, n in agent_seen.counts.items() if k[1] != b"devices"}
    assert forged_cmds == {}, f"a device accepted commands from a wrong role: {forged_cmds}"
    assert forged_frames == {}, f"the agent received forged device frames: {forged_frames}"


def test_each_role_gets_exactly_its_flows(security_dir, secure_router):
    """The declarations the real programs make work under the policy: liveliness, the oracle (case A),
    decisions to the bridge, and the recorder sees everything while it can query nothing.
    """
    oracle_key, alive_key = "cvvc/F/sim/oracle", "cvvc/F/alive/pv/x"
    recorded = _Counter()
    with (_client(secure_router, security_dir, "devices") as device,
          _client(secure_router, security_dir, "agent") as agent,
          _client(secure_router, security_dir, "recorder") as recorder):
        recorder.declare_subscriber("cvvc/**", recorded)

        def on_query(query: zenoh.Query) -> None:
            with query:
                query.reply(oracle_key, b"oracle")

        device.declare_queryable(oracle_key, on_query, complete=True)
        token = device.liveliness().declare_token(alive_key)
        alive: set[str] = set()
        agent.liveliness().declare_subscriber(
            "cvvc/F/alive/**", lambda s: alive.add(str(s.key_expr)), history=True)
        assert wait_for(lambda: alive_key in alive, 5.0), "the agent does not see the device's liveliness"
        replies = [r.ok.payload.to_bytes() for r in agent.get(oracle_key, timeout=5.0) if r.ok is not None]
        assert replies == [b"oracle"]
        assert [r for r in recorder.get(oracle_key, timeout=0.5) if r.ok is not None] == []
        decision = agent.declare_publisher("cvvc/F/agent/decision")
        assert wait_for(lambda: bool(decision.matching_status.matching), 5.0)  # the recorder's subscriber
        decision.put(b"decision")
        device.put("cvvc/F/ack/pv/x", b"ack")
        assert wait_for(lambda: recorded.get("cvvc/F/agent/decision", b"decision") == 1
                        and recorded.get("cvvc/F/ack/pv/x", b"ack") == 1, 5.0)
        token.undeclare()



def _program_args(*flags: str):
    import argparse

    from schemas.bus import add_bus_arguments

    parser = argparse.ArgumentParser()
    add_bus_arguments(parser)
    return parser.parse_args(["--connect", "tcp/127.0.0.1:7447", *flags])


def test_every_program_is_secure_by_default_with_a_local_ca_apart_from_the_role_keys(tmp_path, monkeypatch, caplog):
    """A program given no security flag presents its role's certificate of ``<cache>/security``, issued on first use
    from a CA created without a question in ``<cache>/ca``; ``--insecure`` warns; both flags at once are refused."""
    from schemas.bus import bus_config_from_args

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    cache = tmp_path / "xdg" / "cvvc-edge"
    bus = bus_config_from_args(_program_args(), role="agent")
    assert bus.tls_dir == str(cache / "security") and bus.role == "agent"
    assert role_paths(cache / "ca", "ca")[1].is_file() and not role_paths(cache / "security", "ca")[1].exists()
    assert all(role_paths(cache / "security", r)[0].is_file() for r in ROLES)
    conf = str(zenoh_config(bus))
    assert "tls/127.0.0.1:7447" in conf and "tcp/127.0.0.1:7447" not in conf
    before = role_paths(cache / "security", "agent")[0].read_bytes()
    assert bus_config_from_args(_program_args(), role="devices").tls_dir == bus.tls_dir
    assert role_paths(cache / "security", "agent")[0].read_bytes() == before  # issued once
    with caplog.at_level("WARNING"):
        plain = bus_config_from_args(_program_args("--insecure"), role="agent")
    assert plain.tls_dir is None and "--insecure: the bus runs without TLS" in caplog.text
    with pytest.raises(SystemExit):
        _program_args("--insecure", "--secure-dir", str(tmp_path))


def test_a_security_dir_issued_by_another_ca_is_issued_again(tmp_path):
    d = tmp_path / "security"
    init_ca(tmp_path / "ca1")
    init_security_dir(d, ca_dir=tmp_path / "ca1")
    old = role_paths(d, "agent")[0].read_bytes()
    init_ca(tmp_path / "ca2")
    written = init_security_dir(d, ca_dir=tmp_path / "ca2")
    assert role_paths(d, "agent")[0] in written and role_paths(d, "agent")[0].read_bytes() != old
    assert role_paths(d, "ca")[0].read_bytes() == role_paths(tmp_path / "ca2", "ca")[0].read_bytes()
    with pytest.raises(SecurityError, match="folder of its own"):
        from schemas.security import ensure_local_security

        ensure_local_security(d, ca_dir=d)


def test_a_router_mode_session_of_any_role_enforces_the_policy(security_dir) -> None:
    """A bridge that only listens is the router: it carries the deny-by-default policy even with the devices
    certificate, so its clients are not allowed everything."""
    conf = str(zenoh_config(BusConfig(mode="router", listen=(f"tcp/127.0.0.1:{free_port()}",),
                                      tls_dir=str(security_dir), role="devices")))
    assert '"default_permission":"deny"' in conf.replace(" ", "")
