"""Ecosystem integrations: Foxglove live (foxglove.websocket.v1) and in MCAP, the ROS 2 bridge (rmw_zenoh keys,
CDR), the zenoh-cli codec. Real processes and sessions on loopback, every wait bounded."""

from __future__ import annotations

import asyncio
import json
import math
import os
import struct
import subprocess
import sys
import threading
import time

import msgpack
import pytest

from magmesh_cli import foxglove_types as fx
from schemas import keys, messages
from tests import meshutil as mu

pytestmark = pytest.mark.mesh


def _alarm(vehicle, seq, state="raised", severity="critical"):
    return messages.make("alarm", vehicle, 1.0 + seq, seq, source="dmc", state=state, severity=severity,
                         reason="field strength off by 3000 nT", value=3000.0, threshold=1500.0, unit="nT",
                         service="dmc_detector/a")


HEADING_30 = math.radians(30)


def _heading(vehicle, seq, heading=HEADING_30, pitch=0.05, roll=-0.02):
    return messages.make("heading", vehicle, 0.1 * seq, seq, heading_rad=heading, pitch_rad=pitch, roll_rad=roll,
                         heading_std_rad=0.01, pitch_std_rad=0.01, roll_std_rad=0.01, mode="magnetic",
                         mag_innovation_rad=0.0, mag_test_ratio=0.1, mag_fused=True)


def _gnss(vehicle, seq, lat=32.06, lon=118.80, pos=(0.0, 0.0, 0.0), std=1.5):
    return messages.make("gnss", vehicle, 0.2 * seq, seq, lat_deg=lat, lon_deg=lon, alt_m=10.0,
                         pos_enu_m=list(pos), vel_enu_m_s=[1.0, 0.0, 0.0], course_rad=math.pi / 2, speed_m_s=1.0,
                         fix_type="3d", num_sats=9, pdop=1.2, horiz_std_m=std)


def _geomag(vehicle, seq, pos=(100.0, 200.0, 0.0)):
    return messages.make("geomag_fix", vehicle, 5.0 + seq, seq, status="accepted", accepted=True, pos_enu_m=list(pos),
                         ins_pos_enu_m=[90.0, 210.0, 0.0], hausdorff_nt=4.0, margin_nt=3.0, search_area_m2=1e6,
                         n_samples=20)


# ---- pure conversions --------------------------------------------------------------------------------------------


def test_conversions_give_foxglove_types_with_right_values():
    conv = fx.FoxgloveConverter(origins={"survey-1": (45.4, -75.7, 300.0)})
    t_ns = 1_700_000_000_123_456_789
    log = conv.convert(keys.alarm("car-1", "dmc"), _alarm("car-1", 0), t_ns)
    assert [(o.topic, o.schema) for o in log] == [("/car-1/log", "foxglove.Log")]
    assert log[0].msg["level"] == fx.LOG_ERROR and log[0].msg["timestamp"] == {"sec": 1_700_000_000,
                                                                                "nsec": 123_456_789}
    assert "3000 nT" in log[0].msg["message"] and "threshold 1500 nT" in log[0].msg["message"]
    cleared = conv.convert(keys.alarm("car-1", "dmc"), _alarm("car-1", 1, state="cleared"), t_ns)
    assert cleared[0].msg["level"] == fx.LOG_INFO

    # GNSS 100 m east / 50 m north of the origin: the learned origin puts a later local fix back on the map
    lat, lon, _ = fx.maths.enu_to_geodetic([100.0, 50.0, 2.0], 32.06, 118.80, 8.0)
    gn = conv.convert(keys.clean_gnss("car-1"), _gnss("car-1", 0, float(lat), float(lon), (100.0, 50.0, 2.0)), t_ns)
    assert gn[0].schema == "foxglove.LocationFix" and gn[0].topic == "/car-1/gnss/fix"
    assert gn[0].msg["position_covariance"][0] == pytest.approx(1.5**2) and gn[0].msg["position_covariance_type"] == 2
    o = conv.origin("car-1")
    assert o[0] == pytest.approx(32.06, abs=1e-9) and o[1] == pytest.approx(118.80, abs=1e-9)
    assert conv.convert(keys.raw_gnss("car-1"), _gnss("car-1", 1), t_ns) == []  # raw shown once, after ingest

    fix = conv.convert(keys.fix_geomag("survey-1"), _geomag("survey-1", 0, (0.0, 1000.0, 0.0)), t_ns)
    assert fix[0].topic == "/survey-1/geomag/fix"
    assert fix[0].msg["latitude"] == pytest.approx(45.4 + 1000.0 / 6_367_000 * 180 / math.pi, abs=2e-4)
    assert fix[0].msg["longitude"] == pytest.approx(-75.7, abs=1e-12)
    assert conv.convert(keys.fix_geomag("drone-1"), _geomag("drone-1", 0), t_ns) == []
    assert conv.skipped["geomag fix: no origin"] == 1
    pending = dict(_geomag("survey-1", 1), status="pending", accepted=False)
    assert conv.convert(keys.fix_geomag("survey-1"), pending, t_ns) == []

    # attitude: heading 30° (clockwise from north) is yaw +60° in ENU; at the vehicle's last GNSS position
    pose, tf = conv.convert(keys.heading("car-1"), _heading("car-1", 0, pitch=0.0, roll=0.0), t_ns)
    q = pose.msg["pose"]["orientation"]
    assert 2 * math.atan2(q["z"], q["w"]) == pytest.approx(math.radians(60))
    assert pose.msg["pose"]["position"] == {"x": 100.0, "y": 50.0, "z": 2.0}
    assert (tf.topic, tf.msg["parent_frame_id"], tf.msg["child_frame_id"]) == ("/tf", "car-1/enu", "car-1/base_link")


# ---- Foxglove live -----------------------------------------------------------------------------------------------


def _spawn_cli(*args, env=None):
    e = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    return subprocess.Popen([sys.executable, "-m", "magmesh", *args], cwd=mu.REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=e, start_new_session=True)


class _Publisher:
    """Publishes a vehicle's alarm, heading, GNSS and geomagnetic fixes at ~20 Hz until stopped."""

    def __init__(self, session):
        self.session = session
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        seq = 0
        while not self.stop.is_set():
            s = self.session
            s.put(keys.clean_gnss("car-1"), messages.encode(_gnss("car-1", seq)))
            s.put(keys.heading("car-1"), messages.encode(_heading("car-1", seq)))
            s.put(keys.alarm("car-1", "dmc"), messages.encode(_alarm("car-1", seq, "raised" if seq % 2 else "cleared")))
            s.put(keys.fix_geomag("car-1"), messages.encode(_geomag("car-1", seq)))
            seq += 1
            time.sleep(0.05)


async def _foxglove_client(port, want_topics, timeout_s=150.0, on_live=None):
    """Speak foxglove.websocket.v1: wait for the advertised channels, subscribe, decode a message of each.

    ``on_live`` is called once, when the first live heading arrives (the server's mesh tap is then running)."""
    import websockets

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"])
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    async with ws:
        assert ws.subprotocol == "foxglove.websocket.v1"
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        assert info["op"] == "serverInfo"
        chans: dict[int, dict] = {}
        subs: dict[int, int] = {}
        got: dict[str, dict] = {}
        while set(got) != set(want_topics):
            left = deadline - time.monotonic()
            assert left > 0, f"missing {set(want_topics) - set(got)}; channels {[c['topic'] for c in chans.values()]}"
            frame = await asyncio.wait_for(ws.recv(), left)
            if isinstance(frame, str):
                m = json.loads(frame)
                if m["op"] == "advertise":
                    new = []
                    for c in m["channels"]:
                        chans[c["id"]] = c
                        if c["topic"] in want_topics and c["id"] not in subs.values():
                            sid = len(subs) + 1
                            subs[sid] = c["id"]
                            new.append({"id": sid, "channelId": c["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            assert frame[0] == 0x01
            sid, log_ns = struct.unpack_from("<IQ", frame, 1)
            ch = chans[subs[sid]]
            if on_live is not None and ch["topic"] == "magmesh/car-1/heading":
                on_live()
                on_live = None
            got.setdefault(ch["topic"], {"channel": ch, "msg": json.loads(frame[13:]), "log_ns": log_ns})
        return got


def test_foxglove_live_channels_schemas_and_messages(tmp_path):
    port = mu.free_port()
    ws_port = mu.free_port()
    router = mu.open_router(port)
    pub_session = mu.open_client(port)
    # an alarm raised before the server starts: it learns it by querying, as a late joiner
    early = dict(_alarm("car-1", 0), source="match")
    queryable = pub_session.declare_queryable(
        keys.alarm("car-1", "match"), lambda q: q.reply(keys.alarm("car-1", "match"), messages.encode(early)))
    proc = _spawn_cli("foxglove", "--connect", mu.endpoint(port), "--port", str(ws_port), "--quiet",
                      "--manifest", str(mu.REPO / "deploy" / "mesh.toml"),
                      env={"MAGMESH_STATE_DIR": str(tmp_path)})
    pub = _Publisher(pub_session)
    want = ["magmesh/car-1/alarm/dmc", "magmesh/car-1/alarm/track", "magmesh/car-1/alarm/match", "magmesh/car-1/heading", "magmesh/car-1/fix/geomag", "magmesh/car-1/clean/gnss",
            "/car-1/log", "/car-1/gnss/fix", "/car-1/geomag/fix", "/car-1/pose", "/tf"]
    try:
        # one transition on a key not seen before, while the client is connected: it reaches the client only as
        # the channel's latched latest message (it is sent before the client can subscribe to the new channel)
        got = asyncio.run(_foxglove_client(ws_port, want, on_live=lambda: pub_session.put(
            keys.alarm("car-1", "track"), messages.encode(dict(_alarm("car-1", 0), source="track")))))
    finally:
        pub.stop.set()
        pub.thread.join(5)
        rc = mu.stop(proc, timeout=15)
        out = proc.stdout.read().decode(errors="replace")
        queryable.undeclare()
        pub_session.close()
        router.close()
    assert rc == 0, out
    assert got["magmesh/car-1/alarm/match"]["msg"]["source"] == "match"
    for topic in want[:6]:
        ch = got[topic]["channel"]
        assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
        schema = json.loads(ch["schema"])
        assert ch["schemaName"] == f"magmesh.{messages.type_for_key(topic)}"
        assert set(schema["required"]) >= {"type", "vehicle", "t_s", "seq"}
        # the live message decodes and validates against the magmesh contract
        assert messages.validate(got[topic]["msg"], where=topic)["vehicle"] == "car-1"
    assert got["magmesh/car-1/heading"]["msg"]["heading_rad"] == pytest.approx(math.radians(30))
    for topic, schema_name in [("/car-1/log", "foxglove.Log"), ("/car-1/gnss/fix", "foxglove.LocationFix"),
                               ("/car-1/geomag/fix", "foxglove.LocationFix"), ("/car-1/pose", "foxglove.PoseInFrame"),
                               ("/tf", "foxglove.FrameTransform")]:
        ch = got[topic]["channel"]
        assert ch["schemaName"] == schema_name and ch["encoding"] == "json", ch
        assert set(json.loads(ch["schema"])["required"]) <= set(got[topic]["msg"]), topic
    assert got["/car-1/gnss/fix"]["msg"]["latitude"] == pytest.approx(32.06)
    # the geomagnetic fix (100 m E, 200 m N of the frame origin learned from GNSS) lands north-east of it
    g = got["/car-1/geomag/fix"]["msg"]
    assert 32.06 + 0.0017 < g["latitude"] < 32.06 + 0.0019 and 118.80 + 0.001 < g["longitude"] < 118.80 + 0.0011
    assert got["/car-1/log"]["msg"]["level"] in (fx.LOG_ERROR, fx.LOG_INFO)
    assert "foxglove:" in out and "dropped for slow clients" in out


def test_foxglove_server_counts_every_message_it_does_not_deliver():
    """A client that does not keep up loses its oldest messages, each one counted; nothing vanishes silently."""
    from magmesh_cli.foxglove_ws import FoxgloveServer

    server = FoxgloveServer(port=0, backlog=8).start()
    n = 400
    payload = b"x" * 20_000

    async def run():
        import websockets

        async with websockets.connect(f"ws://127.0.0.1:{server.port}", subprotocols=["foxglove.websocket.v1"],
                                      max_size=None) as ws:
            cid = server.add_channel("/big", "big", json.dumps({"type": "object"}))
            while True:
                m = json.loads(await asyncio.wait_for(ws.recv(), 30))
                if m["op"] == "advertise" and any(c["id"] == cid for c in m["channels"]):
                    break
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 5, "channelId": cid}]}))
            deadline = time.monotonic() + 30
            while not any(c.subs for c in list(server._clients)):
                assert time.monotonic() < deadline
                await asyncio.sleep(0.05)
            for i in range(n):
                server.send(cid, i, payload)
            data, warned = 0, False
            while True:
                st = server.stats()
                if data + st["dropped_slow_client"] + st["dropped_server_behind"] == n:
                    return data, warned, st
                frame = await asyncio.wait_for(ws.recv(), 30)
                if isinstance(frame, bytes):
                    assert struct.unpack_from("<I", frame, 1)[0] == 5 and frame[13:] == payload
                    data += 1
                else:
                    warned = warned or ("too slow" in json.loads(frame).get("message", ""))

    try:
        data, warned, st = asyncio.run(run())
    finally:
        server.stop()
    assert st["dropped_slow_client"] > 0 and warned
    assert data + st["dropped_slow_client"] + st["dropped_server_behind"] == n and data >= 1


def test_foxglove_bad_flags_get_one_clear_paragraph(tmp_path):
    p = _spawn_cli("foxglove", "--origin", "car-1=north", "--port", str(mu.free_port()))
    out = p.communicate(timeout=60)[0].decode()
    assert p.returncode == 2 and "--origin 'car-1=north' must be VEHICLE=LAT,LON" in out and "Traceback" not in out
    p = _spawn_cli("foxglove", "--manifest", str(tmp_path / "missing.toml"))
    out = p.communicate(timeout=60)[0].decode()
    assert p.returncode == 2 and "missing.toml does not exist" in out and "Traceback" not in out


# ---- Foxglove in MCAP --------------------------------------------------------------------------------------------


def _read_mcap(path):
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        r = make_reader(fh)
        return [(sch, ch, m) for sch, ch, m in r.iter_messages(log_time_order=True)]


def test_record_json_writes_jsonschema_json_and_foxglove_types(tmp_path):
    port = mu.free_port()
    router = mu.open_router(port)
    pub_session = mu.open_client(port)
    out = tmp_path / "fox.mcap"
    proc = _spawn_cli("record", "--encoding", "json", "-o", str(out), "--duration", "8", "--quiet",
                      "--connect", mu.endpoint(port), "magmesh/car-1/**", env={"MAGMESH_STATE_DIR": str(tmp_path)})
    pub = _Publisher(pub_session)
    try:
        text = proc.communicate(timeout=120)[0].decode(errors="replace")
    finally:
        pub.stop.set()
        pub.thread.join(5)
        pub_session.close()
        router.close()
    assert proc.returncode == 0, text
    rows = _read_mcap(out)
    by_topic: dict[str, list] = {}
    for sch, ch, m in rows:
        by_topic.setdefault(ch.topic, []).append((sch, ch, m))
    for topic in ("magmesh/car-1/alarm/dmc", "magmesh/car-1/heading", "magmesh/car-1/clean/gnss", "/car-1/log",
                  "/car-1/gnss/fix", "/car-1/geomag/fix", "/car-1/pose", "/tf"):
        assert topic in by_topic, (topic, sorted(by_topic), text)
        sch, ch, m = by_topic[topic][0]
        assert ch.message_encoding == "json" and sch.encoding == "jsonschema", topic
        json.loads(sch.data)
        json.loads(m.data)
    assert by_topic["/car-1/log"][0][0].name == "foxglove.Log"
    assert by_topic["/car-1/gnss/fix"][0][0].name == "foxglove.LocationFix"
    assert by_topic["/car-1/geomag/fix"][0][0].name == "foxglove.LocationFix"
    fix = json.loads(by_topic["/car-1/gnss/fix"][0][2].data)
    assert fix["latitude"] == pytest.approx(32.06) and fix["longitude"] == pytest.approx(118.80)
    logs = [json.loads(m.data) for _, _, m in by_topic["/car-1/log"]]
    alarms = [json.loads(m.data) for _, _, m in by_topic["magmesh/car-1/alarm/dmc"]]
    assert len(logs) == len(alarms) > 10
    assert [lg["level"] for lg in logs] == [fx.LOG_ERROR if a["state"] == "raised" else fx.LOG_INFO for a in alarms]
    # the magmesh channels replay: read back as msgpack messages equal to what was published
    from magmesh_cli import recording as rc

    recs = [r for r in rc.read_records(out) if r.key == "magmesh/car-1/heading"]
    assert len(recs) == len(by_topic["magmesh/car-1/heading"])
    first = recs[0].decode()
    assert first == messages.validate(_heading("car-1", first["seq"]))
    assert all(not r.key.startswith("/") for r in rc.read_records(out))  # Foxglove views are not replayed
    assert "/car-1/log" not in rc.summarize(out)["keys"]


def test_mcap_to_json_foxglove_converts_a_msgpack_recording(tmp_path):
    from magmesh_cli import recording as rc

    src, dst = tmp_path / "run.mcap", tmp_path / "fox.mcap"
    t0 = 1_700_000_000_000_000_000
    with rc.RecordingWriter(src) as w:
        for i in range(5):
            w.write_message(keys.clean_gnss("car-1"), _gnss("car-1", i), t0 + i * 1000)
            w.write_message(keys.alarm("car-1", "dmc"), _alarm("car-1", i), t0 + i * 1000 + 1)
        w.write(keys.raw_imu("car-1"), b"\xc1 not msgpack", t0 + 9000)
    p = _spawn_cli("mcap", "to-json", "--foxglove", str(src), "-o", str(dst))
    text = p.communicate(timeout=60)[0].decode()
    assert p.returncode == 0, text
    assert "wrote 10 JSON messages and 10 Foxglove-typed messages" in text and "1 undecodable kept" in text
    rows = _read_mcap(dst)
    names = {(ch.topic, sch.name if sch else None, ch.message_encoding) for sch, ch, _ in rows}
    assert ("/car-1/log", "foxglove.Log", "json") in names
    assert ("/car-1/gnss/fix", "foxglove.LocationFix", "json") in names
    assert ("magmesh/car-1/raw/imu", None, "application/octet-stream") in names  # kept, not lost


# ---- ROS 2 bridge ------------------------------------------------------------------------------------------------


def test_ros2_bridge_puts_cdr_under_rmw_zenoh_keys_with_tokens(tmp_path):

    from magmesh_cli import ros2
    from schemas import batch

    port = mu.free_port()
    router = mu.open_router(port)
    s = mu.open_client(port)
    got: list[tuple[str, bytes, bytes | None]] = []
    cond = threading.Condition()

    def on(sample):
        with cond:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            got.append((str(sample.key_expr), sample.payload.to_bytes(), att))
            cond.notify_all()

    sub = s.declare_subscriber("7/**", on)
    proc = _spawn_cli("ros2-bridge", "--connect", mu.endpoint(port), "--domain-id", "7", "--quiet",
                      env={"MAGMESH_STATE_DIR": str(tmp_path)})
    store = ros2.typestore("jazzy")
    want = {
        "7/car_1/mag_1/sensor_msgs::msg::dds_::MagneticField_/" + store.hash_rihs01("sensor_msgs/msg/MagneticField"),
        "7/car_1/imu/sensor_msgs::msg::dds_::Imu_/" + store.hash_rihs01("sensor_msgs/msg/Imu"),
        "7/car_1/gnss/fix/sensor_msgs::msg::dds_::NavSatFix_/" + store.hash_rihs01("sensor_msgs/msg/NavSatFix"),
        "7/car_1/heading/geometry_msgs::msg::dds_::QuaternionStamped_/"
        + store.hash_rihs01("geometry_msgs/msg/QuaternionStamped"),
        "7/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/"
        + store.hash_rihs01("diagnostic_msgs/msg/DiagnosticArray"),
        "7/car_1/mag_2/sensor_msgs::msg::dds_::MagneticField_/" + store.hash_rihs01("sensor_msgs/msg/MagneticField"),
    }
    mag = messages.make("mag", "car-1", 1.0, 1, sensor="1", b_nt=[21000.0, -1500.0, -42000.0])
    imu = messages.make("imu", "car-1", 1.0, 1, gyro_rad_s=[0.01, -0.02, 0.3], accel_m_s2=[0.1, 0.2, 9.81])
    cols = batch.from_message(messages.make("mag", "car-1", 1.0, 1, sensor="2", b_nt=[1.0, 2.0, 3.0]))
    deadline = time.monotonic() + 120
    seq = 0
    try:
        while time.monotonic() < deadline:
            seq += 1
            s.put(keys.clean_mag("car-1", "1"), messages.encode(dict(mag, seq=seq)))
            s.put(keys.clean_imu("car-1"), messages.encode(dict(imu, seq=seq)))
            s.put(keys.clean_gnss("car-1"), messages.encode(_gnss("car-1", seq)))
            s.put(keys.heading("car-1"), messages.encode(_heading("car-1", seq)))
            s.put(keys.alarm("car-1", "dmc"), messages.encode(_alarm("car-1", seq)))
            s.put(keys.clean_batch("car-1"), batch.encode("car-1", seq, {"mag/2": cols}))
            with cond:
                if want <= {k for k, _, _ in got}:
                    break
                cond.wait(0.2)
        tokens = [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/7/**", timeout=3.0) if r.ok is not None]
    finally:
        rc = mu.stop(proc, timeout=15)
        out = proc.stdout.read().decode(errors="replace")
        sub.undeclare()
        s.close()
        router.close()
    assert rc == 0, out
    with cond:
        first = {}
        for k, payload, att in got:
            first.setdefault(k, (payload, att))
    assert want <= set(first), (sorted(first), out)

    def des(key, t):
        return store.deserialize_cdr(first[key][0], t)

    k_mag = next(k for k in want if "/mag_1/" in k)
    m = des(k_mag, "sensor_msgs/msg/MagneticField")
    assert (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z) == pytest.approx((21000e-9, -1500e-9, -42000e-9))
    assert m.header.frame_id == "car_1/base_link" and list(m.magnetic_field_covariance) == [0.0] * 9
    m2 = des(next(k for k in want if "/mag_2/" in k), "sensor_msgs/msg/MagneticField")  # from a batch
    assert m2.magnetic_field.z == pytest.approx(3e-9)
    i = des(next(k for k in want if "/imu/" in k), "sensor_msgs/msg/Imu")
    assert (i.angular_velocity.z, i.linear_acceleration.z, i.orientation_covariance[0]) == pytest.approx((0.3, 9.81, -1))
    f = des(next(k for k in want if "/gnss/" in k), "sensor_msgs/msg/NavSatFix")
    assert (f.latitude, f.longitude, f.altitude) == pytest.approx((32.06, 118.80, 10.0))
    assert f.position_covariance[0] == pytest.approx(2.25) and f.position_covariance_type == 2 and f.status.status == 0
    q = des(next(k for k in want if "/heading/" in k), "geometry_msgs/msg/QuaternionStamped").quaternion
    from magmesh import maths

    hdg, pitch, roll = maths.euler_from_quat([q.w, q.x, q.y, q.z])
    assert (hdg, pitch, roll) == pytest.approx((HEADING_30, 0.05, -0.02), abs=1e-9)
    d = des(next(k for k in want if "/diagnostics/" in k), "diagnostic_msgs/msg/DiagnosticArray")
    st = d.status[0]
    assert st.level in (2,) and st.name == "magmesh/car-1/alarm/dmc" and st.hardware_id == "car-1"
    assert {kv.key: kv.value for kv in st.values}["threshold"] == "1500"
    # every put carries rmw_zenoh's attachment: sequence, source timestamp, 16-byte gid
    sq, ts, gid = ros2.parse_attachment(first[k_mag][1])
    assert sq >= 1 and abs(ts - time.time_ns()) < 300e9 and len(gid) == 16
    # liveliness: the node and one publisher per topic, in rmw_zenoh's layout
    assert any(t.split("/")[5] == "NN" and t.endswith("/%/%/magmesh_bridge") for t in tokens), tokens
    pubs = [t.split("/") for t in tokens if t.split("/")[5] == "MP"]
    assert {p[9] for p in pubs} >= {"%car_1%imu", "%car_1%mag_1", "%diagnostics", "%car_1%heading"}, tokens
    imu_tok = next(p for p in pubs if p[9] == "%car_1%imu")
    assert imu_tok[10:] == ["sensor_msgs::msg::dds_::Imu_", store.hash_rihs01("sensor_msgs/msg/Imu"), "1:2:1,10:,:,:,,"]
    assert "ros2-bridge:" in out


def test_ros2_bridge_bad_flags(tmp_path):
    p = _spawn_cli("ros2-bridge", "--domain-id", "999", "--node-name", "9bad")
    out = p.communicate(timeout=60)[0].decode()
    assert p.returncode == 2 and "--domain-id 999" in out and "'9bad' is not a ROS node name" in out
    assert "Traceback" not in out


# ---- zenoh-cli codec ---------------------------------------------------------------------------------------------


def test_zenoh_cli_prints_decoded_magmesh_messages(tmp_path):
    from pathlib import Path

    from magmesh_cli import zenoh_codec

    zenoh_exe = Path(sys.executable).with_name("zenoh")
    assert zenoh_exe.exists(), "zenoh-cli is a dev dependency"
    port = mu.free_port()
    router = mu.open_router(port)
    s = mu.open_client(port)
    p = subprocess.Popen([str(zenoh_exe), "--mode", "client", "--connect", mu.endpoint(port), "subscribe", "-k",
                          "magmesh/**", "--decoder", "magmesh", "--line", "{key} {value}"], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(p.stdout.readline, b"")), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        seq = 0
        while time.monotonic() < deadline:
            seq += 1
            s.put(keys.heading("car-1"), messages.encode(_heading("car-1", seq)))
            s.put(keys.alarm("car-1", "dmc"), messages.encode(_alarm("car-1", seq)))
            time.sleep(0.1)
            text = b"".join(lines).decode(errors="replace")
            if "magmesh/car-1/heading {" in text and "magmesh/car-1/alarm/dmc {" in text:
                break
    finally:
        mu.stop(p, timeout=10)
        s.close()
        router.close()
    rows = [ln.decode().strip().split(" ", 1) for ln in lines if ln.startswith(b"magmesh/")]
    heading = json.loads(next(v for k, v in rows if k == "magmesh/car-1/heading"))
    assert messages.validate(heading)["heading_rad"] == pytest.approx(HEADING_30)
    alarm = json.loads(next(v for k, v in rows if k == "magmesh/car-1/alarm/dmc"))
    assert alarm["reason"] == "field strength off by 3000 nT" and alarm["threshold"] == 1500.0
    # a map that breaks the contract is shown with what is wrong; garbage is refused; the encoder validates
    bad = json.loads(zenoh_codec.decode("magmesh/car-1/heading", msgpack.packb({"type": "heading", "seq": 1})))
    assert "_invalid" in bad and bad["type"] == "heading"
    with pytest.raises(ValueError, match="not msgpack"):
        zenoh_codec.decode("magmesh/car-1/heading", b"\xc1\xc1")
    imu = '{"type":"imu","version":1,"vehicle":"car-1","t_s":1.0,"seq":1,"gyro_rad_s":[0,0,0],"accel_m_s2":[0,0,9.8]}'
    assert messages.decode(zenoh_codec.encode("magmesh/car-1/raw/imu", imu))["accel_m_s2"] == [0.0, 0.0, 9.8]
    with pytest.raises(messages.SchemaError, match="gyro_rad_s"):
        zenoh_codec.encode("magmesh/car-1/raw/imu", imu.replace('"gyro_rad_s":[0,0,0],', ""))


def test_zenohd_recipe_is_a_valid_zenoh_config_with_an_alarm_storage():
    import zenoh

    conf = zenoh.Config.from_file(str(mu.REPO / "deploy" / "zenohd" / "zenohd.json5"))
    assert json.loads(conf.get_json("mode")) == "router"
    store = json.loads(conf.get_json("plugins/storage_manager/storages/magmesh_alarms"))
    assert store["key_expr"] == keys.alarms_all() and store["volume"] == "memory"
    assert json.loads(conf.get_json("timestamping/enabled"))["router"] is True
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


def test_foxglove_layout_refers_only_to_channels_and_fields_magmesh_serves():
    import re

    layout = json.loads((mu.REPO / "deploy" / "foxglove" / "magmesh-layout.json").read_text())
    cfg = layout["configById"]

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    panels = leaves(layout["layout"])
    assert sorted(panels) == sorted(cfg) and {p.split("!")[0] for p in panels} >= {"Map", "3D", "Plot", "RosOut"}
    conv = fx.FoxgloveConverter()
    t = time.time_ns()
    derived = {o.topic: o.schema for k, m in [(keys.alarm("car-1", "dmc"), _alarm("car-1", 0)),
                                               (keys.clean_gnss("car-1"), _gnss("car-1", 0)),
                                               (keys.fix_geomag("car-1"), _geomag("car-1", 0)),
                                               (keys.heading("car-1"), _heading("car-1", 0))]
               for o in conv.convert(k, m, t)}
    m = cfg["Map!magmesh"]
    assert derived[m["followTopic"]] == "foxglove.LocationFix"
    assert all(derived[tp] == "foxglove.LocationFix" for tp in m["topicColors"])
    assert derived[cfg["RosOut!alarms"]["topicToRender"]] == "foxglove.Log"
    assert all(derived[tp] == "foxglove.PoseInFrame" for tp in cfg["3D!magmesh"]["topics"])
    pose, tf = conv.convert(keys.heading("car-1"), _heading("car-1", 1), t)
    assert cfg["3D!magmesh"]["followTf"] == tf.msg["child_frame_id"]
    paths = [p["value"] for k, c in cfg.items() if k.startswith("Plot") for p in c["paths"]]
    paths.append(cfg["RawMessages!dmc"]["topicPath"])
    for path in paths:
        topic, field_ = re.fullmatch(r'"([^"]+)"(?:\.(\w+))?(?:\[\d+\])?', path).groups()
        mt = messages.MESSAGES[messages.type_for_key(topic)]
        assert keys.parse(topic).vehicle == "car-1"
        if field_:
            assert field_ in {f.name for f in mt.fields}, path
