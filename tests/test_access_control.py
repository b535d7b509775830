"""Access control: the secured mesh of ``magmesh up --secure``, with the real simulator and services.

``magmesh up --secure DIR`` makes the certificates (one per vehicle of the manifest, services, operators) and
runs its router with mutual TLS and the rules of :mod:`magmesh_cli.secure`, and the car simulator, ingest and the
DMC detector each with its role's certificate (declared publishers, subscribers, liveliness, queries). The car's
whole stream must reach ``dmc``. Every denial is proven against an allowed twin: the same action by the
certificate that may do it arrives (or is answered) within the same wait, and the denied one does not.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
from meshutil import REPO, free_port, query_status, stop, wait_alive

from magmesh_cli import secure
from schemas import keys, messages

pytestmark = pytest.mark.mesh

SECURE = REPO / "deploy" / "secure"
DRIVE_S = 24.0
SPEED = 2.0


def open_as(port: int, pki: Path, cert: str | None, ca: Path | None = None):
    """A client session of the secured mesh with certificate ``cert`` of ``pki`` (None: no client certificate)."""
    import zenoh

    from magmesh import zconf

    cfg = [f"transport/link/tls/root_ca_certificate:{json.dumps(str(ca or pki / 'ca.pem'))}",
           "transport/link/tls/verify_name_on_connect:true"]
    if cert:
        cfg += [f"transport/link/tls/connect_certificate:{json.dumps(str(pki / (cert + '.pem')))}",
                f"transport/link/tls/connect_private_key:{json.dumps(str(pki / (cert + '.key')))}",
                "transport/link/tls/enable_mtls:true"]
    conf = zconf.build_config(connect=[f"tls/127.0.0.1:{port}"], cfg=cfg)
    conf.insert_json5("connect/timeout_ms", "4000")  # an unauthorised client must fail, not wait forever
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

    def has(self, tag: bytes) -> bool:
        with self.lock:
            return any(tag in b for _, b in self.items)

    def count(self, key: str) -> int:
        with self.lock:
            return sum(1 for k, _ in self.items if k == key)

    def msgs(self, key: str) -> list[dict]:
        with self.lock:
            return [msgpack.unpackb(b) for k, b in self.items if k == key]


def wait_until(pred, timeout: float, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(interval)
    return pred()


def raw_imu(vehicle: str, t_s: float, tag: str) -> bytes:
    return messages.encode(messages.make("imu", vehicle, t_s, 0, gyro_rad_s=[0.0, 0.0, 0.0],
                                         accel_m_s2=[0.0, 0.0, 9.81], tag=tag), check=False)


def alarm_payload(vehicle: str, tag: str) -> bytes:
    return messages.encode(messages.make(
        "alarm", vehicle, 1.0, 0, source="dmc", state="raised", severity="critical", reason=tag, value=1.0,
        threshold=0.5, service=tag))


def proven_denied(cases, wait_s: float = 15.0, settle_s: float = 1.0) -> None:
    """Independent ``(observe, allowed, denied)`` cases (tags of their own) on the same mesh, proven together: each
    case's ``denied()`` then its ``allowed()``, case after case; ``observe(tag)`` sees every allowed tag and,
    ``settle_s`` after the last of them arrived, none of the denied."""
    for _observe, allowed, denied in cases:
        denied()
        allowed()
    deadline = time.monotonic() + wait_s
    for i, (observe, _allowed, _denied) in enumerate(cases):
        assert wait_until(lambda observe=observe: observe("allowed"), max(0.0, deadline - time.monotonic())), (
            f"case {i}: the allowed twin never arrived: the proof would be empty")
    time.sleep(settle_s)  # each denied action was sent before its twin: had it passed it would be here by now
    for i, (observe, _allowed, _denied) in enumerate(cases):
        assert not observe("denied"), f"case {i}: the denied action went through"


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("secure")
    pki, foreign = tmp / "pki", tmp / "foreign"
    # a certificate of the mesh's authority but of no role, and a whole other authority
    subprocess.run(["bash", str(SECURE / "make-certs.sh"), str(pki)], check=True, capture_output=True,
                   env=dict(os.environ, EXTRA_CLIENTS="intruder"))
    subprocess.run(["bash", str(SECURE / "make-certs.sh"), str(foreign)], check=True, capture_output=True)
    port = free_port()
    sup = subprocess.Popen(
        [sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--secure", str(pki),
         "--endpoint", f"tcp/127.0.0.1:{port}", "--only", "sim-car-1,ingest-1,dmc-1", "--duration", "300",
         "--log-dir", str(tmp / "logs"), "--set", f"sim-car-1.speed={SPEED}", "--set", "sim-car-1.loop=false",
         "--set", f"sim-car-1.duration_s={DRIVE_S}"],
        cwd=REPO, stdout=open(tmp / "up.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True,
        env={**os.environ, "MAGMESH_STATE_DIR": str(tmp / "state")})
    sessions = []
    try:
        op = None
        deadline = time.monotonic() + 60
        while op is None:  # the router may take seconds to start on a busy machine
            try:
                op = open_as(port, pki, "operator")
            except Exception:
                if time.monotonic() > deadline or sup.poll() is not None:
                    raise AssertionError(
                        f"the secured mesh did not come up: {(tmp / 'up.log').read_text()[-2000:]}") from None
                time.sleep(0.5)
        sessions.append(op)
        dmc = Inbox(op, keys.dmc("car-1"))
        for role, inst in (("ingest", "ingest-1"), ("dmc_detector", "dmc-1"), ("sim", "sim-car-1")):
            assert wait_alive(op, keys.svc_token(role, inst), 90), f"{inst} never came up on the secured mesh"
        yield dict(port=port, pki=pki, foreign=foreign, op=op, dmc=dmc, sessions=sessions, tmp=tmp)
    finally:
        for s in sessions:
            try:
                s.close()
            except Exception:
                pass
        stop(sup, 15)


def test_secured_mesh_carries_the_cars_full_stream(secured):
    op = secured["op"]

    def counts():
        car = query_status(op, keys.svc_status("sim", "sim-car-1")) or {}
        det = query_status(op, keys.svc_status("dmc_detector", "dmc-1")) or {}
        ing = query_status(op, keys.svc_status("ingest", "ingest-1")) or {}
        n = lambda st, side, k: st.get(side, {}).get(k, {}).get("n", 0)  # noqa: E731
        return (n(car, "out", keys.raw_mag("car-1", "1")), n(ing, "out", keys.clean_mag("car-1", "1")),
                n(det, "out", keys.dmc("car-1")))

    expected = int(DRIVE_S * 50) + 1  # 50 Hz magnetometer, one drive (both ends sampled)
    assert wait_until(lambda: counts()[0] >= expected, 120), f"the car did not finish its drive: {counts()}"
    last: list = [None]

    def settled() -> bool:  # the three equal, and still so a second later (the car's last sample may be in flight)
        now = counts()
        same = len(set(now)) == 1 and now == last[0]
        last[0] = now
        return same

    assert wait_until(settled, 30, interval=1.0), f"published / cleaned / dmc differ: {counts()}"
    published, cleaned, epochs = last[0]
    assert published >= expected and published == cleaned == epochs
    seqs = [m["seq"] for m in secured["dmc"].msgs(keys.dmc("car-1"))]
    assert seqs and seqs[-1] == epochs - 1, "the operator did not see the last dmc epoch"
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "dmc epochs missing at the operator"
    print(f"\nsecured mesh: car published {published} mag/1 samples, ingest cleaned {cleaned}, "
          f"dmc published {epochs} epochs; operator saw {len(seqs)} (seq {seqs[0]}..{seqs[-1]}, contiguous)")


def test_roles_are_enforced_with_positive_proofs(secured, capsys):
    m = secured
    port, pki, op = m["port"], m["pki"], m["op"]

    def client(cert, ca=None):
        s = open_as(port, pki, cert, ca)
        m["sessions"].append(s)
        return s

    proofs: list[str] = []
    car1, survey1, service, intruder = (client("vehicle-car-1"), client("vehicle-survey-1"), client("service"),
                                        client("intruder"))
    # watched from a second operator session: a session's own subscribers see its own puts
    watch = Inbox(client("operator"), "magmesh/survey-1/**")
    time.sleep(1.0)  # declarations reach the router

    # a vehicle's certificate publishes its own raw keys only
    cases = [(lambda t: watch.has(f"raw-{t}".encode()),
              lambda: survey1.put(keys.raw_imu("survey-1"), raw_imu("survey-1", 1.0, "raw-allowed")),
              lambda: car1.put(keys.raw_imu("survey-1"), raw_imu("survey-1", 1.0, "raw-denied")))]
    proofs.append("car-1's certificate publishing survey-1's raw keys (survey-1's own certificate: delivered)")

    # only services publish alarms, cal/params and clean (ten cases in all, each with tags of its own)
    for what, key, payload in (("an alarm", keys.alarm("survey-1", "dmc"), lambda t: alarm_payload("survey-1", t)),
                               ("cal/params", keys.cal_params("survey-1", "1"), lambda t: f"cal-{t}".encode()),
                               ("clean/", keys.clean_imu("survey-1"), lambda t: raw_imu("survey-1", 2.0, t))):
        for who, sess in (("a vehicle", survey1), ("an operator", op), ("a certificate of no role", intruder)):
            tag = f"{what}-{who}"
            cases.append((lambda t, tag=tag: watch.has(f"{tag}-{t}".encode()),
                          lambda key=key, payload=payload, tag=tag: service.put(key, payload(f"{tag}-allowed")),
                          lambda key=key, payload=payload, tag=tag, sess=sess: sess.put(key, payload(f"{tag}-denied"))))
            proofs.append(f"{who} publishing {what} (a service: delivered)")
    proven_denied(cases)

    # only services (and the simulators, under magmesh/svc/sim/) answer status queries
    def answerer(key, tag):
        def on_query(q):
            q.reply(key, msgpack.packb({"instance": tag}))
        return car1.declare_queryable(key, on_query)

    fake_sim = answerer(keys.svc_status("sim", "probe-allowed"), "probe-allowed")
    fake_svc = answerer(keys.svc_status("ingest", "probe-denied"), "probe-denied")
    time.sleep(1.0)

    def status_instances():
        out = set()
        for r in op.get(keys.svc_status_all(), timeout=3.0):
            if r.ok is not None:
                try:
                    out.add(msgpack.unpackb(r.ok.payload.to_bytes()).get("instance"))
                except Exception:
                    out.add("<garbage>")
        return out

    got = status_instances()
    assert "probe-allowed" in got and "ingest-1" in got, f"allowed status answers missing: {got}"
    assert "probe-denied" not in got and "<garbage>" not in got, f"a vehicle answered a service's status: {got}"
    fake_sim.undeclare()
    fake_svc.undeclare()
    proofs.append("a vehicle answering a service's status query (its own under svc/sim/: answered)")

    # only operators call control keys (a harmless op: the supervisor answers it with an error, ingest with its state)
    calls = [(target, who, sess) for target in (keys.svc_control("supervisor", "main"), keys.svc_control("ingest", "ingest-1"))
             for who, sess in (("a service", service), ("a vehicle", car1), ("a certificate of no role", intruder))]
    answers: dict[int, list] = {}

    def call(i, sess, target):
        req = msgpack.packb({"op": "state" if "ingest" in target else "nop"})
        answers[i] = [r for r in sess.get(target, payload=req, timeout=5.0) if r.ok is not None]

    threads = [threading.Thread(target=call, args=(i, sess, target)) for i, (target, _, sess) in enumerate(calls)]
    for t in threads:  # the denied calls run while the operator's twins are answered
        t.start()
    for target, _who, _ in calls:
        req = msgpack.packb({"op": "state" if "ingest" in target else "nop"})
        allowed = [r for r in op.get(target, payload=req, timeout=5.0) if r.ok is not None]
        assert len(allowed) == 1, f"the operator's control query to {target} was not answered"
    for t in threads:
        t.join(15)
    for i, (target, who, _) in enumerate(calls):
        assert answers.get(i) == [], f"{who} called {target}: {answers.get(i)}"
        proofs.append(f"{who} calling {target.split('/')[2]}'s control key (an operator: answered)")

    # reading: only services and operators; proven by the operator's twin subscription receiving the same put
    readers = {who: Inbox(s, "magmesh/survey-1/**") for who, s in (("a vehicle", car1), ("no role", intruder))}
    time.sleep(1.0)
    survey1.put(keys.raw_imu("survey-1"), raw_imu("survey-1", 3.0, "read-probe"))
    service.put(keys.alarm("survey-1", "probe"), alarm_payload("survey-1", "read-probe-alarm"))
    assert wait_until(lambda: watch.has(b"read-probe") and watch.has(b"read-probe-alarm"), 15)
    time.sleep(1.0)
    for who, box in readers.items():
        assert not box.has(b"read-probe"), f"{who} read raw data or alarms"
        proofs.append(f"{who} reading raw/ and alarms (the operator: received)")

    # authentication: no certificate, another authority (the right certificate connects: the sessions above)
    import zenoh

    for what, pki_dir, cert in (("no client certificate", pki, None),
                                ("a certificate of another authority", m["foreign"], "operator")):
        with pytest.raises(zenoh.ZError):
            m["sessions"].append(open_as(port, pki_dir, cert))
        proofs.append(f"{what}: connection refused in the TLS handshake")
    with capsys.disabled():
        print(f"\n---- access control: {len(proofs)} denials, each against an allowed twin ----")
        for p in proofs:
            print("  " + p)


def test_router_file_matches_the_generated_rules():
    text = (SECURE / "router.json5").read_text()
    conf = json.loads("\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//")))
    from magmesh_cli.supervisor import load_manifest

    vehicles = secure.manifest_vehicles(load_manifest(REPO / "deploy" / "mesh.toml"))
    assert conf["access_control"] == secure.access_control(vehicles)
    assert {s["id"] for s in conf["access_control"]["subjects"]} >= {f"vehicle-{v}" for v in vehicles}


def test_up_refuses_an_open_endpoint_beyond_loopback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--endpoint",
                        "tcp/0.0.0.0:7999", "--duration", "1", "--log-dir", str(tmp_path)],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and "--insecure" in r.stderr and "--secure" in r.stderr
    assert len([ln for ln in r.stderr.strip().splitlines() if ln.strip()]) == 1, "one paragraph"
    assert secure.exposure_error("tcp/10.1.2.3:7447", None, secure=False, insecure=True) is None
    assert secure.exposure_error("tcp/127.0.0.1:7447", None, secure=False, insecure=False) is None
    assert secure.exposure_error("tcp/[::1]:7447", None, secure=False, insecure=False) is None
    assert secure.exposure_error("tcp/10.1.2.3:7447", None, secure=False, insecure=False) is not None
    assert secure.exposure_error("tcp/10.1.2.3:7447", str(SECURE / "router.json5"), False, False) is None
    assert re.search(r"publish calibration parameters", r.stderr)
