"""The secured mesh: certificates, the router's access-control rules per role, and each role's client file.

Every process presents a certificate of the mesh's own authority; its common name (CN) is its role:

- ``magmesh-service``: the services. Subscribe to everything; publish the derived keys (``clean/``,
  ``rejects``, ``cal/``, ``dmc``, ``heading``, ``fix/``, ``track``, ``alarm/``); answer queries (status,
  control, alarms, cal/params). The only query they call is the calibration services' status (to confirm
  parameters before adopting them): no control key of another process.
- ``magmesh-vehicle-{vehicle}``: one per vehicle of the manifest. Publishes that vehicle's ``raw/`` and
  ``truth/`` keys only, reads nothing, and may answer status only under ``magmesh/svc/sim/``.
- ``magmesh-operator``: operators' tools. Subscribe to everything and call any query (status, alarms,
  ``magmesh swap`` through the supervisor's control key); publish nothing.

Anything else (another CN, no certificate, another authority) gets nothing: ``default_permission`` is deny,
and a client without a certificate of the authority does not get past the TLS handshake.

``magmesh up --secure DIR`` calls :func:`prepare` (certificates made if absent, configuration files written)
and runs the router and every process of the manifest with them. ``python -m magmesh_cli.secure MANIFEST DIR``
does the preparation alone (to copy the files to other hosts).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from magmesh import zconf
from magmesh.paths import DEPLOY_DIR
from schemas import keys

MAKE_CERTS = DEPLOY_DIR / "secure" / "make-certs.sh"
R = keys.ROOT
#: the keys only services publish (per vehicle: magmesh/{vehicle}/...)
SERVICE_OUTPUTS = ("clean/**", "rejects", "cal/**", "dmc", "heading", "fix/**", "track", "alarm/**")
#: Zenoh's advanced publisher/subscriber (alarm and cal/params caches, heartbeats, detection tokens)
ADV = f"{R}/**/@adv/**"


def vehicle_cn(vehicle: str) -> str:
    return f"magmesh-vehicle-{keys.check_id(vehicle)}"


def vehicle_cert_name(vehicle: str) -> str:
    return f"vehicle-{keys.check_id(vehicle)}"


def _rule(rid: str, flows: list[str], messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rid, "permission": "allow", "flows": flows, "messages": messages, "key_exprs": key_exprs}


def access_control(vehicles: list[str], operators: list[str] | None = None) -> dict:
    """The router's ``access_control`` section for these vehicles (one subject and policy per vehicle)."""
    svc = f"{R}/{keys.SVC}"
    rules = [
        # ---- services ----
        _rule("service-publish", ["ingress"], ["put", "delete"],
              [f"{R}/*/{k}" for k in SERVICE_OUTPUTS] + [f"{R}/*/alarm/**/@adv/**", f"{R}/*/cal/**/@adv/**"]),
        # subscriber declarations flow to publishers: without them a declared publisher stops sending after its
        # first sample (it has no matching subscriber as far as it knows)
        _rule("service-subscribe", ["ingress", "egress"], ["declare_subscriber"], [f"{R}/**", ADV]),
        _rule("service-receive", ["egress"], ["put", "delete"], [f"{R}/**", ADV]),
        _rule("service-answer", ["ingress"], ["declare_queryable", "reply"], [f"{R}/**", ADV]),
        _rule("service-asked", ["egress"], ["query"], [f"{R}/**", ADV]),
        # a service confirms a cal/params sample with the calibration services' status before adopting it
        _rule("service-confirm", ["ingress"], ["query"], [f"{svc}/calibration/*/status"]),
        _rule("service-confirmed", ["egress"], ["reply"], [f"{svc}/calibration/*/status"]),
        _rule("service-presence", ["ingress"], ["liveliness_token"], [f"{svc}/**", ADV]),
        _rule("service-watch", ["ingress"], ["declare_liveliness_subscriber", "liveliness_query"], [f"{svc}/**"]),
        _rule("service-watch-receive", ["egress"], ["liveliness_token"], [f"{svc}/**"]),
        # ---- operators ----
        _rule("operator-watch", ["ingress"], ["declare_subscriber", "declare_liveliness_subscriber",
                                              "liveliness_query", "query"], [f"{R}/**", ADV]),
        _rule("operator-receive", ["egress"], ["put", "delete", "liveliness_token", "reply"], [f"{R}/**", ADV]),
        _rule("operator-presence", ["ingress"], ["liveliness_token"], [ADV]),
    ]
    subjects = [{"id": "services", "cert_common_names": ["magmesh-service"]},
                {"id": "operators", "cert_common_names": ["magmesh-operator"] + [f"magmesh-{o}" for o in operators or []]}]
    policies = [{"id": "services", "subjects": ["services"],
                 "rules": ["service-publish", "service-subscribe", "service-receive", "service-answer", "service-asked",
                           "service-confirm", "service-confirmed", "service-presence", "service-watch", "service-watch-receive"]},
                {"id": "operators", "subjects": ["operators"],
                 "rules": ["operator-watch", "operator-receive", "operator-presence"]}]
    # a vehicle's simulator or recorder may answer status and control queries, but only as a publisher (sim)
    rules.append(_rule("vehicle-presence", ["ingress"], ["liveliness_token", "declare_queryable", "reply"],
                       [f"{svc}/sim/*", f"{svc}/sim/*/status", f"{svc}/sim/*/control"]))
    rules.append(_rule("vehicle-asked", ["egress"], ["query"],
                       [f"{svc}/*/*/status", f"{svc}/sim/*/status", f"{svc}/sim/*/control"]))
    # subscriber declarations reach the vehicles: a declared publisher sends only to matching subscribers it
    # knows of (without these it stops after its first sample). The rule's key must include the subscription's
    # (a service subscribes to magmesh/*/raw/**), so it is wide; it lets a vehicle see what others subscribe to,
    # never the data.
    rules.append(_rule("vehicle-matching", ["egress"], ["declare_subscriber"], [f"{R}/**"]))
    for v in sorted(set(vehicles)):
        own = [f"{R}/{keys.check_id(v)}/raw/**", f"{R}/{v}/truth/**"]
        rules.append(_rule(f"vehicle-{v}-publish", ["ingress"], ["put", "delete"], own))
        subjects.append({"id": f"vehicle-{v}", "cert_common_names": [vehicle_cn(v)]})
        policies.append({"id": f"vehicle-{v}", "subjects": [f"vehicle-{v}"],
                         "rules": [f"vehicle-{v}-publish", "vehicle-matching", "vehicle-presence", "vehicle-asked"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _tls(pki: Path, cert: str, listen: bool) -> dict:
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": str(pki / "ca.pem"), f"{side}_certificate": str(pki / f"{cert}.pem"),
            f"{side}_private_key": str(pki / f"{cert}.key"), "enable_mtls": True, "verify_name_on_connect": True}


def router_config(pki: Path, listen: list[str], vehicles: list[str], connect: list[str] | None = None,
                  operators: list[str] | None = None) -> dict:
    conf = {"mode": "router", "listen": {"endpoints": list(listen)}, "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tx": zconf.transport_tx(), "tls": _tls(pki, "router", listen=True)}},
            "access_control": access_control(vehicles, operators)}
    if connect:
        conf["connect"] = {"endpoints": list(connect), "timeout_ms": -1}
    return conf


def client_config(pki: Path, cert: str, connect: list[str]) -> dict:
    return {"mode": "client", "connect": {"endpoints": list(connect), "timeout_ms": -1},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tx": zconf.transport_tx(), "tls": _tls(pki, cert, listen=False)}}}


def tls_endpoint(endpoint: str) -> str:
    """``tcp/HOST:PORT`` → ``tls/HOST:PORT`` (the secured mesh listens with TLS only)."""
    proto, sep, rest = endpoint.partition("/")
    if not sep:
        raise ValueError(f"endpoint {endpoint!r} is not PROTOCOL/HOST:PORT")
    return endpoint if proto == "tls" else f"tls/{rest}"


def make_certs(pki: Path, vehicles: list[str], sans: list[str] | None = None, extra: list[str] | None = None) -> None:
    """Certificates for the authority, the router, the services, the operators and every vehicle; those already
    in ``pki`` are kept (an existing authority signs the missing ones)."""
    names = [vehicle_cert_name(v) for v in sorted(set(vehicles))] + list(extra or [])
    env = dict(os.environ, EXTRA_CLIENTS=" ".join(names))
    r = subprocess.run(["bash", str(MAKE_CERTS), str(pki), *(sans or [])], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{MAKE_CERTS.name} failed (exit {r.returncode}): {(r.stderr or r.stdout).strip()[-800:]}")


def manifest_vehicles(manifest) -> list[str]:
    vs = set(manifest.vehicles)
    vs.update(p.vehicle for p in manifest.processes if p.vehicle)
    return sorted(vs)


def write_json(path: Path, obj: dict) -> Path:
    path.write_text("// written by magmesh (magmesh/secure.py); JSON is JSON5\n" + json.dumps(obj, indent=2) + "\n")
    return path


def prepare(pki: Path, vehicles: list[str], endpoint: str, sans: list[str] | None = None) -> dict:
    """Make what is missing in ``pki`` and write the router's and each role's configuration files there.

    Returns {"router": path, "service": path, "operator": path, "vehicles": {vehicle: path}, "endpoint": tls}."""
    pki = Path(pki).resolve()
    pki.mkdir(parents=True, exist_ok=True)
    ep = tls_endpoint(endpoint)
    host = ep.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
    extra_sans = list(sans or [])
    if host not in ("localhost", "127.0.0.1") and host not in extra_sans:
        extra_sans.append(host)
    make_certs(pki, vehicles, extra_sans)
    out = {"endpoint": ep, "router": write_json(pki / "router.json5", router_config(pki, [ep], vehicles)),
           "service": write_json(pki / "client-service.json5", client_config(pki, "service", [ep])),
           "operator": write_json(pki / "client-operator.json5", client_config(pki, "operator", [ep])),
           "vehicles": {}}
    for v in vehicles:
        out["vehicles"][v] = write_json(pki / f"client-{vehicle_cert_name(v)}.json5",
                                        client_config(pki, vehicle_cert_name(v), [ep]))
    return out


def client_config_for(prepared: dict, spec) -> str:
    """The configuration file a process of the manifest runs with on the secured mesh."""
    if spec.is_publisher:
        v = spec.vehicle
        if not v or v not in prepared["vehicles"]:
            raise ValueError(f"process {spec.name!r} publishes but names no vehicle of the manifest: on the secured "
                             f"mesh a publisher's certificate is bound to one vehicle (set vehicle = \"...\")")
        return str(prepared["vehicles"][v])
    return str(prepared["service"])


DEFAULT_DIR = Path(".magmesh") / "secure"
LOOPBACK = ("localhost", "::1")


def is_loopback(endpoint: str) -> bool:
    """True when a Zenoh endpoint can only be reached from this host (loopback address or a local socket)."""
    proto, _, rest = endpoint.partition("/")
    if proto.startswith("unixsock") or proto == "unixpipe":
        return True
    host = rest.split("#", 1)[0].rsplit(":", 1)[0].strip("[]").lower()
    return host in LOOPBACK or host.startswith("127.")


def config_is_secured(path: str) -> bool:
    """A router configuration file with access control on and TLS listeners only."""
    import zenoh

    conf = zenoh.Config.from_file(path)
    acl = json.loads(conf.get_json("access_control/enabled") or "false")
    listen = json.loads(conf.get_json("listen/endpoints") or "[]")
    if isinstance(listen, dict):  # per-mode endpoints
        listen = [e for v in listen.values() for e in (v or [])]
    return bool(acl) and bool(listen) and all(str(e).startswith("tls/") for e in listen)


def exposure_error(endpoint: str, zenoh_config: str | None, secure: bool, insecure: bool) -> str | None:
    """The paragraph `magmesh up` refuses with when it would open the mesh beyond this host unprotected."""
    if secure or insecure or is_loopback(endpoint):
        return None
    if zenoh_config and config_is_secured(zenoh_config):
        return None
    return (f"magmesh up: refusing to host the mesh on {endpoint} without TLS and access control. Anyone who "
            f"can reach that address could publish calibration parameters, forge or clear alarms, and call the "
            f"control keys that stop, restart or swap services. Run it secured with `magmesh up --secure` "
            f"(certificates and rules are made for you, see deploy/README.md), keep it on a loopback endpoint "
            f"such as tcp/127.0.0.1:7447, or accept the risk explicitly with --insecure.")


def secure_supervisor(sup, manifest, pki: Path, sans: list[str] | None = None) -> dict:
    """Prepare ``pki`` and switch a :class:`~magmesh_cli.supervisor.Supervisor` to the secured mesh."""
    prepared = prepare(pki, manifest_vehicles(manifest), sup.endpoint, sans)
    for spec in manifest.processes:  # refuse before starting anything
        if spec.enabled:
            client_config_for(prepared, spec)
    manifest.zenoh_config = str(prepared["router"])
    sup.endpoint = prepared["endpoint"]
    sup.client_config = lambda spec: client_config_for(prepared, spec)
    return prepared


def main(argv: list[str] | None = None) -> int:
    import argparse

    from .supervisor import load_manifest

    p = argparse.ArgumentParser(prog="python -m magmesh_cli.secure",
                                description="Make the secured mesh's certificates (if absent) and configuration files.")
    p.add_argument("manifest", help="mesh manifest (TOML): its vehicles get one certificate each")
    p.add_argument("dir", help="where certificates and configuration files go")
    p.add_argument("--endpoint", default=None, help="the router's endpoint (default: the manifest's, as tls/)")
    p.add_argument("--san", action="append", default=[], help="another name or address of the router (repeatable)")
    a = p.parse_args(argv)
    m = load_manifest(a.manifest)
    out = prepare(Path(a.dir), manifest_vehicles(m), a.endpoint or m.endpoint, a.san)
    print(f"secured mesh on {out['endpoint']}: router {out['router']}\n  services  {out['service']}\n"
          f"  operators {out['operator']}")
    for v, f in out["vehicles"].items():
        print(f"  {v:10s}{f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
