"""magmesh messages as ROS 2 standard types over rmw_zenoh: names, key expressions, tokens and CDR.

Pure Python (rosbags for the types and CDR, no Zenoh here); ``magmesh ros2-bridge`` puts the results on the
mesh. A ROS 2 node running rmw_zenoh (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``) connected to the same Zenoh
router sees the bridge as a node with publishers, and receives the messages.

rmw_zenoh's conventions (its ``liveliness_utils.cpp``, ``attachment_helpers.cpp``):

- data key expression ``<domain_id>/<topic without leading slash>/<dds type>/<type hash>``, e.g.
  ``0/car_1/imu/sensor_msgs::msg::dds_::Imu_/RIHS01_7d9a…``; the dds type of ``pkg/msg/Name`` is
  ``pkg::msg::dds_::Name_``; the type hash is RIHS01 (REP 2011) computed by rosbags from the type's
  definition for jazzy, ``TypeHashNotSupported`` for humble;
- liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP>/<enclave>/<namespace>/<node>`` for the
  node and, for each publisher, ``…/<topic>/<dds type>/<type hash>/<qos>``, every ``/`` inside a name
  replaced by ``%``; the QoS chunk is ``reliability:durability:history,depth:deadline:lifespan:liveliness``
  (``1:2:1,10:,:,:,,`` = reliable, volatile, keep last 10, defaults for the rest);
- each put carries an attachment: int64 sequence number, int64 source timestamp (ns), and the publisher's
  16-byte gid, in zenoh-ext serialization (little endian; the gid as a length-prefixed byte sequence).

The mapping (units: SI as ROS wants them; frames: ROS REP 103 is magmesh's own, ENU and FLU body):

======================  ==================================  ================================================
magmesh key             ROS 2 topic / type                  conversion
======================  ==================================  ================================================
clean/mag/{s}           /{v}/mag_{s}                        ``b_nt`` × 1e-9 → ``magnetic_field`` (T), FLU
                        sensor_msgs/msg/MagneticField       body (frame ``{v}/base_link``); covariance all
                                                            zero = unknown (ROS convention)
cal/mag/{s}             /{v}/mag_{s}/calibrated (same type) hard/soft iron removed
clean/imu               /{v}/imu  sensor_msgs/msg/Imu       ``gyro_rad_s`` → angular_velocity (rad/s),
                                                            ``accel_m_s2`` → linear_acceleration (m/s²);
                                                            no orientation (orientation_covariance[0] = -1),
                                                            other covariances unknown (0)
clean/gnss              /{v}/gnss/fix                       lat/lon (°), ``alt_m`` (above the WGS 84
                        sensor_msgs/msg/NavSatFix           ellipsoid, as ROS); covariance ENU diagonal
                                                            (h², h², (2h)²) from ``horiz_std_m`` (type
                                                            DIAGONAL_KNOWN), else UNKNOWN; fix_type none →
                                                            NO_FIX, 2d/3d → FIX, dgps → SBAS_FIX, rtk → GBAS
heading                 /{v}/heading                        body (FLU) → ENU orientation from heading, pitch,
                        geometry_msgs/msg/QuaternionStamped  roll (frame ``{v}/enu``); the 1-σ uncertainties
                                                            have no field in this type
alarm/{source}          /diagnostics                        one DiagnosticStatus per transition: raised
                        diagnostic_msgs/msg/DiagnosticArray critical → ERROR, raised warning → WARN, cleared →
                                                            OK; name ``magmesh/{v}/alarm/{source}``,
                                                            hardware_id the vehicle, values: state,
                                                            severity, value, threshold, unit, service
======================  ==================================  ================================================

``{v}`` is the vehicle id made a ROS name token (``car-1`` → ``car_1``: letters, digits and ``_`` only, not
starting with a digit). Header stamps are the receive time by default (ROS nodes compare them with their
own clock), or the sample time ``t_s``.
"""

from __future__ import annotations

import hashlib
import math
import re
import struct
from dataclasses import dataclass

import numpy as np

from magmesh import maths

DISTROS = ("jazzy", "humble")
ADMIN_SPACE = "@ros2_lv"
QOS_RELIABLE_VOLATILE_KEEP_LAST_10 = "1:2:1,10:,:,:,,"
NO_TYPE_HASH = "TypeHashNotSupported"

MAG = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTICS_TOPIC = "/diagnostics"


def typestore(distro: str = "jazzy"):
    from rosbags.typesys import Stores, get_typestore

    if distro not in DISTROS:
        raise ValueError(f"ROS 2 distribution must be one of {', '.join(DISTROS)}, got {distro!r}")
    return get_typestore(Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_HUMBLE)


def ros_name(text: str) -> str:
    """A magmesh id as a ROS name token (letters, digits, ``_``; not starting with a digit)."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return s if s and not s[0].isdigit() else f"v_{s}"


def mangle(name: str) -> str:
    return name.replace("/", "%")


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/Imu`` → ``sensor_msgs::msg::dds_::Imu_`` (the type name rmw_zenoh puts in keys)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(store, ros_type: str, distro: str) -> str:
    return store.hash_rihs01(ros_type) if distro != "humble" else NO_TYPE_HASH


def topic_key(domain_id: int, topic: str, ros_type: str, thash: str) -> str:
    return f"{int(domain_id)}/{topic.strip('/')}/{dds_type(ros_type)}/{thash}"


def node_token(domain_id: int, zid: str, nid: int, node: str, namespace: str = "/", enclave: str = "/") -> str:
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(nid), str(nid), "NN", mangle(enclave),
                     mangle(namespace), mangle(node)])


def publisher_token(domain_id: int, zid: str, nid: int, eid: int, node: str, topic: str, ros_type: str,
                    thash: str, namespace: str = "/", enclave: str = "/",
                    qos: str = QOS_RELIABLE_VOLATILE_KEEP_LAST_10) -> str:
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(nid), str(eid), "MP", mangle(enclave),
                     mangle(namespace), mangle(node), mangle(topic), dds_type(ros_type), thash, qos])


def gid_of(token: str) -> bytes:
    """A publisher's 16-byte gid: a hash of its liveliness token (unique per publisher, as in rmw_zenoh)."""
    return hashlib.sha256(token.encode()).digest()[:16]


def attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-message attachment (zenoh-ext serialization of int64, int64, uint8[16])."""
    if len(gid) != 16:
        raise ValueError("a gid is 16 bytes")
    return struct.pack("<qqB", int(seq), int(source_timestamp_ns), 16) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    if len(data) != 33 or data[16] != 16:
        raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, ts = struct.unpack_from("<qq", data)
    return seq, ts, bytes(data[17:])


@dataclass(frozen=True)
class RosOut:
    """One ROS 2 message to publish: topic, type and the rosbags message object."""

    topic: str
    ros_type: str
    msg: object


class RosConverter:
    """magmesh messages → ROS 2 standard messages (see the module doc for the mapping)."""

    def __init__(self, store, stamp: str = "receive"):
        if stamp not in ("receive", "sample"):
            raise ValueError(f"stamp must be 'receive' or 'sample', got {stamp!r}")
        self.store = store
        self.stamp = stamp
        t = store.types
        self.T = t
        self._Header, self._Time = t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"]
        self._Vec3, self._Quat = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]

    def _header(self, msg: dict, receive_ns: int, frame_id: str):
        if self.stamp == "receive":
            ns = int(receive_ns)
        else:
            t = msg.get("t_s") or 0.0
            ns = int(round(t * 1e9)) if math.isfinite(t) and t > 0 else 0
        return self._Header(stamp=self._Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
                            frame_id=frame_id)

    def convert(self, info, msg: dict, receive_ns: int) -> list[RosOut]:
        """``info``: the parsed magmesh key (:func:`schemas.keys.parse`)."""
        v = ros_name(info.vehicle)
        t = msg["type"]
        T = self.T
        if t == "mag" and info.kind in ("clean", "cal"):
            b = np.asarray(msg["b_nt"], float) * 1e-9
            sensor = re.sub(r"[^A-Za-z0-9_]", "_", info.sensor)
            topic = f"/{v}/mag_{sensor}" + ("/calibrated" if info.kind == "cal" else "")
            m = T[MAG](header=self._header(msg, receive_ns, f"{v}/base_link"),
                       magnetic_field=self._Vec3(x=float(b[0]), y=float(b[1]), z=float(b[2])),
                       magnetic_field_covariance=np.zeros(9))
            return [RosOut(topic, MAG, m)]
        if t == "imu" and info.kind == "clean":
            g, a = msg["gyro_rad_s"], msg["accel_m_s2"]
            oc = np.zeros(9)
            oc[0] = -1.0  # orientation not provided
            m = T[IMU](header=self._header(msg, receive_ns, f"{v}/base_link"),
                       orientation=self._Quat(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=oc,
                       angular_velocity=self._Vec3(x=g[0], y=g[1], z=g[2]), angular_velocity_covariance=np.zeros(9),
                       linear_acceleration=self._Vec3(x=a[0], y=a[1], z=a[2]),
                       linear_acceleration_covariance=np.zeros(9))
            return [RosOut(f"/{v}/imu", IMU, m)]
        if t == "gnss" and info.kind == "clean":
            S = T["sensor_msgs/msg/NavSatStatus"]
            status = {"none": S.STATUS_NO_FIX, "2d": S.STATUS_FIX, "3d": S.STATUS_FIX, "dgps": S.STATUS_SBAS_FIX,
                      "rtk_float": S.STATUS_GBAS_FIX, "rtk_fixed": S.STATUS_GBAS_FIX}[msg["fix_type"]]
            std = msg.get("horiz_std_m")
            F = T[NAVSATFIX]
            if std is not None:
                h2 = float(std) ** 2
                cov, ctype = np.array([h2, 0, 0, 0, h2, 0, 0, 0, 4 * h2], float), F.COVARIANCE_TYPE_DIAGONAL_KNOWN
            else:
                cov, ctype = np.zeros(9), F.COVARIANCE_TYPE_UNKNOWN
            m = F(header=self._header(msg, receive_ns, f"{v}/gnss"),
                  status=S(status=status, service=S.SERVICE_GPS),
                  latitude=msg["lat_deg"], longitude=msg["lon_deg"], altitude=msg["alt_m"],
                  position_covariance=cov, position_covariance_type=ctype)
            return [RosOut(f"/{v}/gnss/fix", NAVSATFIX, m)]
        if t == "heading":
            w, x, y, z = maths.quat_from_euler(msg["heading_rad"], msg["pitch_rad"], msg["roll_rad"])
            m = T[QUATERNION_STAMPED](header=self._header(msg, receive_ns, f"{v}/enu"),
                                      quaternion=self._Quat(x=float(x), y=float(y), z=float(z), w=float(w)))
            return [RosOut(f"/{v}/heading", QUATERNION_STAMPED, m)]
        if t == "alarm":
            D, KV = T["diagnostic_msgs/msg/DiagnosticStatus"], T["diagnostic_msgs/msg/KeyValue"]
            raised = msg["state"] == "raised"
            level = (D.ERROR if msg["severity"] == "critical" else D.WARN) if raised else D.OK

            def s(x):
                return "" if x is None else (f"{x:g}" if isinstance(x, float) else str(x))

            values = [KV(key=k, value=s(msg.get(k))) for k in
                      ("state", "severity", "value", "threshold", "unit", "service", "raised_t_s", "t_s")
                      if k in msg]
            st = D(level=level, name=info.key, message=msg["reason"], hardware_id=info.vehicle, values=values)
            m = T[DIAGNOSTIC_ARRAY](header=self._header(msg, receive_ns, ""), status=[st])
            return [RosOut(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, m)]
        return []

    def serialize(self, out: RosOut) -> bytes:
        """CDR (little endian, with the encapsulation header) as rmw_zenoh carries it."""
        return bytes(self.store.serialize_cdr(out.msg, out.ros_type))
