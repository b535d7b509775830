"""Access control: mutual TLS and the router's rules in deploy/secure/router.json5, with real processes.

A router (``magmesh router --config deploy/secure/router.json5``) and the real ingest service run on loopback
with certificates made for the test by ``deploy/secure/make-certs.sh``. The test shows that the authorised
roles work end to end (publisher → raw → ingest → clean → operator; a service's alarm reaches operators; an
operator queries status) and that every unauthorised attempt is refused: fake alarms from a publisher, an
operator or a certificate of no role; raw data read by a publisher or by a certificate of no role;
publishing around ingest on clean/; clients with no certificate or one from another authority.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import msgpack
import pytest
from meshutil import REPO, free_port, query_status, stop, wait_alive

from schemas import keys, messages

pytestmark = pytest.mark.mesh

SECURE = REPO / "deploy" / "secure"


def tls_cfg(pki, role: str | None, ca: str = "ca.pem") -> list[str]:
    """--cfg entries of a client with the certificate of ``role`` (None: no client certificate)."""
    out = [f'transport/link/tls/root_ca_certificate:{json.dumps(str(pki / ca))}']
    if role:
        out += [f'transport/link/tls/connect_certificate:{json.dumps(str(pki / (role + ".pem")))}',
                f'transport/link/tls/connect_private_key:{json.dumps(str(pki / (role + ".key")))}',
                "transport/link/tls/enable_mtls:true"]
    return out


def open_tls_client(port: int, pki, role: str | None, ca: str = "ca.pem"):
    import zenoh

    from magmesh import zconf

    conf = zconf.build_config(connect=[f"tls/localhost:{port}"], cfg=tls_cfg(pki, role, ca))
    conf.insert_json5("connect/timeout_ms", "3000")  # an unauthorised client must fail, not wait forever
    return zenoh.open(conf)


class Inbox:
    """Payloads received on one subscription."""

    def __init__(self, session, keyexpr: str):
        self.items: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(keyexpr, self._on)

    def _on(self, sample) -> None:  # tiny callback: append only
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self) -> list[bytes]:
        with self.lock:
            return [b for _, b in self.items]


def wait_until(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def alarm_payload(tag: str) -> bytes:
    return messages.encode(messages.make(
        "alarm", "car-1", 1.0, 0, source="dmc", state="raised", severity="critical", reason=tag, value=1.0,
        threshold=0.5, service=tag))


@pytest.fixture(scope="module")
def secure_mesh(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("secure")
    pki, foreign = tmp / "pki", tmp / "foreign"
    env = dict(os.environ, EXTRA_CLIENTS="intruder")
    subprocess.run([str(SECURE / "make-certs.sh"), str(pki)], check=True, env=env, capture_output=True)
    subprocess.run([str(SECURE / "make-certs.sh"), str(foreign)], check=True, capture_output=True)
    port = free_port()
    router_cfg = [f"transport/link/tls/{k}:{json.dumps(str(pki / f))}" for k, f in (
        ("root_ca_certificate", "ca.pem"), ("listen_certificate", "router.pem"), ("listen_private_key", "router.key"))]
    procs = []
    log = open(tmp / "router.log", "ab")
    args = [sys.executable, "-m", "magmesh", "router", "--config", str(SECURE / "router.json5"),
            "--listen", f"tls/127.0.0.1:{port}", "--name", "secure"]
    for c in router_cfg:
        args += ["--cfg", c]
    procs.append(subprocess.Popen(args, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
    # the service runs from the deploy file; only the test's certificate paths and port differ
    ingest_args = [sys.executable, "-m", "services.ingest", "--config", str(SECURE / "client-service.json5"),
                   "--connect", f"tls/localhost:{port}", "--instance", "ingest-s"]
    for c in tls_cfg(pki, "service"):
        ingest_args += ["--cfg", c]
    procs.append(subprocess.Popen(ingest_args, cwd=REPO, stdout=open(tmp / "ingest.log", "ab"),
                                  stderr=subprocess.STDOUT, start_new_session=True))
    sessions = []
    try:
        operator = None
        deadline = time.monotonic() + 30
        while operator is None:  # the router may take seconds to start on a busy machine
            try:
                operator = open_tls_client(port, pki, "operator")
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.3)
        sessions.append(operator)
        assert wait_alive(operator, keys.svc_token("ingest", "ingest-s"), 60), "ingest never came up over TLS"
        yield dict(port=port, pki=pki, foreign=foreign, operator=operator, sessions=sessions, tmp=tmp)
    finally:
        for s in sessions:
            try:
                s.close()
            except Exception:
                pass
        for p in procs:
            stop(p)


def test_authorised_roles_work_and_unauthorised_are_refused(secure_mesh, capsys):
    m = secure_mesh
    port, pki, op = m["port"], m["pki"], m["operator"]
    sessions = m["sessions"]

    def client(role, ca="ca.pem", pki_dir=None):
        s = open_tls_client(port, pki_dir or pki, role, ca)
        sessions.append(s)
        return s

    alarms = Inbox(op, keys.alarms_all())
    clean = Inbox(op, keys.clean_all())
    service = client("service")
    service_raw = Inbox(service, keys.raw_all())
    publisher_reader = client("publisher")
    publisher_raw = Inbox(publisher_reader, keys.raw_all())
    intruder = client("intruder")  # a certificate of the mesh's authority, but of no role
    intruder_raw = Inbox(intruder, keys.raw_all())
    intruder_alarms = Inbox(intruder, keys.alarms_all())
    time.sleep(1.0)  # subscriptions propagate to the router

    # ---- what is allowed ----
    publisher = client("publisher")
    for i in range(5):
        publisher.put(keys.raw_mag("car-1", "1"), messages.encode(messages.make(
            "mag", "car-1", 10.0 + i, i, sensor="1", b_nt=[20000.0, 1000.0, -40000.0])))
    service.put(keys.alarm("car-1", "dmc"), alarm_payload("authorised-service"))
    assert wait_until(lambda: len(clean.payloads()) >= 5, 10), "raw → ingest → clean did not reach the operator"
    assert wait_until(lambda: b"authorised-service" in b"".join(alarms.payloads()), 5), \
        "a service's alarm did not reach the operator"
    assert len(service_raw.payloads()) == 5, "a service could not read raw data"
    status = query_status(op, keys.svc_status("ingest", "ingest-s"))
    assert status is not None and status["in"], "the operator could not query a service's status"

    # ---- what is refused ----
    denials: list[str] = []
    client("publisher").put(keys.alarm("car-1", "dmc"), alarm_payload("fake-from-publisher"))
    client("operator").put(keys.alarm("car-1", "dmc"), alarm_payload("fake-from-operator"))
    intruder.put(keys.alarm("car-1", "dmc"), alarm_payload("fake-from-intruder"))
    client("publisher").put(keys.clean_mag("car-1", "1"), messages.encode(messages.make(
        "mag", "car-1", 99.0, 0, sensor="1", b_nt=[1.0, 2.0, 3.0])))  # around ingest
    client("publisher").put(keys.heading("car-1"), b"fake heading")
    time.sleep(1.5)
    got = b"".join(alarms.payloads())
    for tag in ("fake-from-publisher", "fake-from-operator", "fake-from-intruder"):
        assert tag.encode() not in got, f"{tag} reached the operator"
        denials.append(f"alarm injection by {tag.removeprefix('fake-from-')}: refused")
    assert all(msgpack.unpackb(b)["t_s"] != 99.0 for b in clean.payloads()), "a publisher wrote on clean/"
    denials.append("publisher writing clean/ (around ingest): refused")
    assert not publisher_raw.payloads(), "a publisher read raw data"
    denials.append("publisher reading raw/: refused")
    # (its own fake alarm reaches its own subscriber inside its session; nothing from the mesh may)
    assert not intruder_raw.payloads(), "a certificate of no role read raw data"
    assert b"authorised-service" not in b"".join(intruder_alarms.payloads()), "a certificate of no role read alarms"
    denials.append("certificate of no role reading raw/ and alarms: refused")
    for what, args in (("no client certificate", (None,)), ("certificate of another authority",
                                                            ("operator", "ca.pem", m["foreign"]))):
        import zenoh

        with pytest.raises(zenoh.ZError):
            client(*args)
        denials.append(f"{what}: connection refused (TLS handshake)")
    with capsys.disabled():
        print("\n---- access control ----")
        print(f"authorised: 5 raw samples → ingest → {len(clean.payloads())} clean at the operator; "
              f"service alarm delivered; status query answered")
        print(f"denials: {len(denials)}")
        for d in denials:
            print("  " + d)
