"""``magmesh ros2-bridge``: republish magmesh streams as ROS 2 standard messages for rmw_zenoh.

    magmesh ros2-bridge                          # ROS domain 0, jazzy type hashes, every vehicle
    magmesh ros2-bridge --domain-id 7 --vehicles 'car-$*' --distro humble

The bridge is a ROS 2 node (default /magmesh_bridge) on the Zenoh mesh: it announces itself and its
publishers with rmw_zenoh's liveliness tokens and puts CDR-encoded messages under rmw_zenoh's key
expressions, so ``ros2 topic list`` / ``ros2 topic echo /car_1/imu`` on a machine running
``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` against the same Zenoh router shows them:

  /<v>/mag_<s>            sensor_msgs/msg/MagneticField   clean magnetometer (T, FLU body)
  /<v>/mag_<s>/calibrated sensor_msgs/msg/MagneticField   calibrated magnetometer
  /<v>/imu                sensor_msgs/msg/Imu             gyro (rad/s), accelerometer (m/s²), FLU body
  /<v>/gnss/fix           sensor_msgs/msg/NavSatFix       GNSS fix
  /<v>/heading            geometry_msgs/msg/QuaternionStamped  fused attitude, body → ENU
  /diagnostics            diagnostic_msgs/msg/DiagnosticArray  alarm transitions

(<v>: the vehicle id as a ROS name, car-1 → car_1.) Alarms are put with blocking congestion control (never
dropped); the sensor streams, like rmw_zenoh's keep-last publishers, let Zenoh drop for a slow ROS
subscriber rather than slow the mesh down.
"""

from __future__ import annotations

import argparse
import logging
import re
import signal
import sys
import threading
import time
from collections import Counter

from magmesh import zconf
from schemas import keys, messages

from ..ros2 import (
    DIAGNOSTICS_TOPIC,
    DISTROS,
    RosConverter,
    attachment,
    gid_of,
    node_token,
    publisher_token,
    topic_key,
    type_hash,
    typestore,
)
from ..tap import decode_samples, run_tap

log = logging.getLogger("magmesh_cli.ros2")
_ROS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ROS_NS = re.compile(r"^/([A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*)?$")


def register(subparsers) -> None:
    p = subparsers.add_parser("ros2-bridge", help="republish magmesh streams as ROS 2 messages (rmw_zenoh)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID of the ROS 2 nodes (default 0)")
    p.add_argument("--distro", choices=DISTROS, default="jazzy",
                   help="ROS 2 distribution of the subscribers: jazzy puts RIHS01 type hashes in the keys "
                        "(default), humble rmw_zenoh's TypeHashNotSupported")
    p.add_argument("--vehicles", default="*", metavar="PATTERN", help="vehicle id or pattern (default all)")
    p.add_argument("--node-name", default="magmesh_bridge", help="ROS node name of the bridge")
    p.add_argument("--namespace", default="/", help="ROS namespace of the bridge node (default /)")
    p.add_argument("--stamp", choices=["receive", "sample"], default="receive",
                   help="header stamps: receive time (default) or the sample time t_s")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    p.add_argument("--quiet", "-q", action="store_true", help="no periodic count lines")
    zconf.add_zenoh_args(p)
    p.set_defaults(func=run)


class Ros2Bridge:
    """magmesh samples → rmw_zenoh publishers (declared, with their liveliness tokens, as topics appear)."""

    def __init__(self, session, domain_id: int, distro: str, node: str, namespace: str, stamp: str):
        import zenoh

        self.zenoh = zenoh
        self.session = session
        self.domain_id, self.distro, self.node, self.namespace = domain_id, distro, node, namespace
        self.store = typestore(distro)
        self.conv = RosConverter(self.store, stamp)
        self.zid = str(session.info.zid())
        self.nid = 0
        self.tokens = [session.liveliness().declare_token(node_token(domain_id, self.zid, self.nid, node, namespace))]
        self._pubs: dict[tuple[str, str], tuple] = {}
        self._next_eid = 1
        self.counts: Counter = Counter()
        self.published: Counter = Counter()

    def _publisher(self, topic: str, ros_type: str):
        p = self._pubs.get((topic, ros_type))
        if p is None:
            z = self.zenoh
            thash = type_hash(self.store, ros_type, self.distro)
            full = topic if self.namespace == "/" else f"{self.namespace}{topic}"
            key = topic_key(self.domain_id, full, ros_type, thash)
            eid = self._next_eid
            self._next_eid += 1
            token = publisher_token(self.domain_id, self.zid, self.nid, eid, self.node, full, ros_type, thash,
                                    self.namespace)
            cc = z.CongestionControl.BLOCK if topic == DIAGNOSTICS_TOPIC else z.CongestionControl.DROP
            pub = self.session.declare_publisher(key, encoding=z.Encoding.APPLICATION_CDR, congestion_control=cc,
                                                 reliability=z.Reliability.RELIABLE)
            self.tokens.append(self.session.liveliness().declare_token(token))
            p = self._pubs[(topic, ros_type)] = (pub, gid_of(token), [0])
            log.info("publishing %s (%s) on %s", full, ros_type, key)
        return p

    def on_sample(self, key: str, payload: bytes, receive_ns: int) -> None:
        try:
            samples = decode_samples(key, payload)
        except (messages.SchemaError, keys.KeyError_, KeyError):
            self.counts["undecodable"] += 1
            return
        for skey, msg in samples:
            info = keys.parse(skey)
            outs = self.conv.convert(info, msg, receive_ns)
            if not outs:
                self.counts["no ROS 2 mapping"] += 1  # e.g. clean/ins, clean/route: skipped by design
            for out in outs:
                pub, gid, seq = self._publisher(out.topic, out.ros_type)
                seq[0] += 1
                pub.put(self.conv.serialize(out), attachment=attachment(seq[0], time.time_ns(), gid))
                self.published[out.topic] += 1

    def close(self) -> None:
        for pub, _, _ in self._pubs.values():
            pub.undeclare()
        for t in self.tokens:
            t.undeclare()


def key_exprs(vehicles: str) -> list[str]:
    """Disjoint subscriptions on what the bridge maps."""
    return [keys.clean_all(vehicles), keys.cal_mag(vehicles, "*"), keys.heading(vehicles), keys.alarms_all(vehicles)]


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    problems = []
    if not (0 <= args.domain_id <= 232):
        problems.append(f"--domain-id {args.domain_id} is outside ROS 2's domain range 0-232")
    if not _ROS_NAME.match(args.node_name):
        problems.append(f"--node-name {args.node_name!r} is not a ROS node name (a letter, then letters, digits, _)")
    if not _ROS_NS.match(args.namespace):
        problems.append(f"--namespace {args.namespace!r} is not a ROS namespace (e.g. / or /fleet)")
    try:
        exprs = key_exprs(args.vehicles)
        conf = zconf.config_from_args(args)
    except (keys.KeyError_, ValueError) as e:
        problems.append(str(e))
    if problems:
        print("magmesh ros2-bridge: " + "; ".join(problems) + ".", file=sys.stderr)
        return 2
    import zenoh

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    last = [time.monotonic()]
    where = ", ".join(args.connect or []) or (args.config or zconf.default_endpoint())
    print(f"connecting to the mesh at {where} (waiting for its router if it is not up yet)", flush=True)
    with zenoh.open(conf) as session:
        bridge = Ros2Bridge(session, args.domain_id, args.distro, args.node_name, args.namespace, args.stamp)
        print(f"ROS 2 bridge: node {args.namespace.rstrip('/')}/{args.node_name} in domain {args.domain_id} "
              f"({args.distro}), zid {bridge.zid}", flush=True)

        def tick() -> None:
            if not args.quiet and time.monotonic() - last[0] >= 10.0:
                last[0] = time.monotonic()
                print(_summary(bridge), flush=True)

        try:
            run_tap(session, exprs, bridge.on_sample, stop, args.duration, on_tick=tick)
        finally:
            bridge.close()
    print(_summary(bridge), flush=True)
    return 0


def _summary(bridge: Ros2Bridge) -> str:
    per = ", ".join(f"{t} {n}" for t, n in sorted(bridge.published.items()))
    return (f"ros2-bridge: {sum(bridge.published.values())} messages on {len(bridge.published)} topics"
            f"{' (' + per + ')' if per else ''}; {bridge.counts['undecodable']} undecodable, "
            f"{bridge.counts['no ROS 2 mapping']} without a ROS 2 mapping (skipped by design)")
