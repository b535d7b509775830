"""Declared services (magmesh/declare.py): what every service and implementation declares is what it does.

For each of them: the subscriptions are the keys its INPUTS give (checked against the templates independently of the
builders, for its default settings and for settings that move its sensors and switch its optional inputs; and, for the
default settings, against the keys the services subscribed to before they were declared), every setting has a
description and ``--help`` shows it with its declared range, and a value outside a declared range or choice stops the
process with one paragraph naming the service, the setting, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
from meshutil import REPO

from magmesh import declare
from magmesh.runtime import SimPublisher, build_settings, make_parser, service_from_args
from magmesh_cli.supervisor import implementations

MODULES = ("services.ingest", "services.calibration", "services.dmc_detector", "services.heading_fuser",
           "services.geomag_matcher", "services.track_monitor", "sim_publishers.car", "sim_publishers.multirotor",
           "sim_publishers.replay", "sim_publishers.survey")
CLASSES = {f"{m}:{name}": cls for m in MODULES for name, cls in implementations(m)[0].items()}

#: what each service subscribed to by hand before it was declared (default settings, every vehicle)
BEFORE = {
    "services.ingest:ingest": ["magmesh/*/raw/**"],
    "services.calibration:calibration": ["magmesh/*/clean/mag/*", "magmesh/*/clean/imu", "magmesh/*/clean/gnss"],
    "services.dmc_detector:threshold": ["magmesh/*/clean/mag/1", "magmesh/*/clean/mag/2", "magmesh/*/cal/params/1",
                                        "magmesh/*/cal/params/2"],
    "services.dmc_detector:fcm": ["magmesh/*/clean/mag/1", "magmesh/*/clean/mag/2", "magmesh/*/cal/params/1",
                                  "magmesh/*/cal/params/2"],
    "services.dmc_detector:single": ["magmesh/*/clean/mag/1", "magmesh/*/cal/params/1"],
    "services.dmc_detector:quasistatic": ["magmesh/*/clean/mag/1", "magmesh/*/clean/imu", "magmesh/*/cal/params/1"],
    "services.dmc_detector:gyro_track": ["magmesh/*/clean/mag/1", "magmesh/*/clean/mag/2", "magmesh/*/clean/imu",
                                         "magmesh/*/cal/params/1", "magmesh/*/cal/params/2"],
    "services.heading_fuser:ekf": ["magmesh/*/clean/imu", "magmesh/*/cal/mag/1", "magmesh/*/clean/mag/1",
                                   "magmesh/*/cal/params/1", "magmesh/*/dmc"],
    "services.heading_fuser:vqf": ["magmesh/*/clean/imu", "magmesh/*/cal/mag/1", "magmesh/*/clean/mag/1",
                                   "magmesh/*/cal/params/1", "magmesh/*/dmc"],
    "services.geomag_matcher:hausdorff_ssda": ["magmesh/*/clean/mag/*", "magmesh/*/clean/ins"],
    "services.track_monitor:track_monitor": ["magmesh/*/clean/route", "magmesh/*/clean/gnss",
                                             "magmesh/*/clean/attitude", "magmesh/*/clean/mag/1"],
    "sim_publishers.car:car": [], "sim_publishers.multirotor:multirotor": [], "sim_publishers.replay:replay": [],
    "sim_publishers.survey:survey": [],
}


def test_every_service_and_implementation_is_covered():
    assert set(CLASSES) == set(BEFORE)


def _variants(cls) -> list[dict]:
    """Settings that move every input: each sensor-naming setting to other ids (one of them empty when it is a single
    optional sensor), each switch of an optional input both ways, each value a ``when`` names."""
    out: list[dict] = [{}]
    names = {f.name: f for f in dataclasses.fields(cls.Settings)} if cls.Settings else {}
    for i in cls.INPUTS:
        if i.sensors not in (None, "*"):
            sensors = (i.sensors,) if isinstance(i.sensors, str) else i.sensors
            out.append({s: str(7 + k) for k, s in enumerate(sensors)})
            if len(sensors) == 1 and names[sensors[0]].default == "1" and i.when is not None:
                out.append({sensors[0]: ""})
        if isinstance(i.when, str):
            out.append({i.when: not names[i.when].default})
        elif i.when is not None:
            name, value = i.when
            for v in value if isinstance(value, tuple) else (value,):
                out.append({name: v})
    unique = {tuple(sorted(v.items())): v for v in out}
    return list(unique.values())


def _expected(cls, settings, pattern: str) -> list[str]:
    """Every active input's keys by its template (str.format: independent of the key builders)."""
    out = []
    for i in cls.INPUTS:
        if isinstance(i.when, str) and not getattr(settings, i.when):
            continue
        if isinstance(i.when, tuple) and getattr(settings, i.when[0]) != i.when[1]:
            continue
        if i.sensors is None:
            out.append(i.template.format(vehicle=pattern))
            continue
        names = ("*",) if i.sensors == "*" else (i.sensors,) if isinstance(i.sensors, str) else i.sensors
        for n in names:
            ids = ["*"] if n == "*" else [getattr(settings, n)]
            out += [i.template.format(vehicle=pattern, sensor=s) for s in ids if s]
    return out


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_subscriptions_are_what_the_declarations_give(name):
    cls = CLASSES[name]
    assert cls(instance="t-1").subscriptions() == BEFORE[name]
    variants = _variants(cls)
    assert len(variants) > 1 or all(i.sensors in (None, "*") and i.when is None for i in cls.INPUTS)
    seen = set()
    for values in variants:
        settings = build_settings(cls.Settings, values)
        for pattern in ("*", "car-$*", "drone-2"):
            svc = cls(settings, instance="t-1", vehicle_pattern=pattern)
            subs = svc.subscriptions()
            assert subs == _expected(cls, settings, pattern), (values, pattern)
            seen.add(tuple(subs))
    assert len(seen) >= (6 if len(variants) > 1 else 3) or not cls.INPUTS  # the variants did move the inputs


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_every_setting_is_described_and_help_shows_it(name):
    cls = CLASSES[name]
    info = declare.settings_info(cls.Settings)
    assert info, f"{name} declares no settings"
    text = " ".join(make_parser(cls).format_help().split())
    for s in info:
        assert len(s.doc.split()) >= 2, f"{name}: setting {s.name} has no description ({s.doc!r})"
        assert s.name in text and " ".join(s.doc.split()) in text, f"{name}: --help does not show {s.name}: {s.doc}"
        if s.allowed:
            assert s.allowed in text, f"{name}: --help does not show the range of {s.name}"
        s.check(s.default)  # every default is one its declaration allows
    for d in (*cls.INPUTS, *cls.OUTPUTS):
        assert d.short in text and " ".join(d.doc.split()) in text, d
    assert ("consumes: -" in text) == (not cls.INPUTS) and cls.OUTPUTS


def _bad_values(s: declare.SettingInfo) -> list:
    """Values just outside what a setting allows."""
    if s.choices is not None:
        return ["no-such-choice"]
    as_int = s.type == "int"
    step = 1 if as_int else 0.5
    out = []
    if s.lo is not None:
        out.append(s.lo - step)
    if s.gt is not None:
        out.append(s.gt)
    if s.hi is not None:
        out.append(s.hi + step)
    if s.lt is not None:
        out.append(s.lt)
    return [int(v) if as_int else float(v) for v in out]


def _args(cls, *sets: str):
    return make_parser(cls).parse_args([a for x in sets for a in ("--set", x)])


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_a_value_outside_a_declared_range_stops_with_one_paragraph(name):
    cls = CLASSES[name]
    declared = [s for s in declare.settings_info(cls.Settings) if s.allowed]
    assert declared, f"{name} declares no range or choice"
    for s in declared:
        for bad in _bad_values(s):
            with pytest.raises(SystemExit) as e:
                service_from_args(cls, _args(cls, f"{s.name}={bad}"))
            msg = str(e.value.code)
            assert "\n" not in msg and msg.startswith(f"{cls.role} ({cls.impl}): setting {s.name} "), msg
            assert repr(bad) in msg and s.allowed in msg, msg
    svc = service_from_args(cls, _args(cls))  # the defaults pass
    assert isinstance(svc, cls) and (isinstance(svc, SimPublisher) or svc.subscriptions() == BEFORE[name])


def test_a_value_that_is_not_a_number_names_the_setting():
    cls = CLASSES["services.ingest:ingest"]
    with pytest.raises(SystemExit) as e:
        service_from_args(cls, _args(cls, "batch_window_s=soon"))
    assert str(e.value.code).startswith("ingest (ingest): setting batch_window_s 'soon' is not float"), e.value.code


@pytest.mark.parametrize("module, setting, value, allowed", [
    ("services.ingest", "batch_window_s", "9", "(0, 5] s"),
    ("services.dmc_detector", "severity", "loud", "warning | critical"),
    ("services.calibration", "improve_ratio", "1.5", "(0, 1]"),
    ("services.heading_fuser", "publish_period_s", "-1", "≥ 0 s"),
    ("services.geomag_matcher", "subdivisions", "40", "[1, 16]"),
    ("services.track_monitor", "mag_source", "raw", "clean | cal"),
    ("sim_publishers.replay", "rate_hz", "0", "> 0 Hz"),
])
def test_the_process_exits_non_zero_with_one_paragraph(module, setting, value, allowed):
    r = subprocess.run([sys.executable, "-m", module, "--set", f"{setting}={value}", "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    err = r.stderr.strip()
    assert r.returncode != 0 and "Traceback" not in r.stderr and "\n" not in err, r.stderr
    assert f"setting {setting} " in err and value in err and allowed in err and f"python -m {module} --help" in err, err


def test_settings_described_by_source_comments():
    """A Settings class written without setting() (the heading filter's core.Settings) takes its descriptions from its
    comments: the trailing one, continued while a parenthesis stays open or by a line starting with "(", else the
    comment block above."""
    src_cls = _commented()
    docs = declare.comment_docs(src_cls)
    assert docs == {"a_s": "the first (its unit is s, continued)", "b": "group heading over two lines",
                    "c_m": "group heading over two lines", "d_nt": "its own (one line) (more detail)"}
    info = {s.name: s for s in declare.settings_info(src_cls)}
    assert info["a_s"].unit == "s" and info["c_m"].unit == "m" and info["d_nt"].unit == "nT" and info["b"].unit == ""


def _commented():
    @dataclasses.dataclass(frozen=True)
    class Commented:
        a_s: float = 1.0  # the first (its unit is
        # s, continued)
        # group heading over
        # two lines
        b: bool = True
        c_m: float = 2.0
        d_nt: float = 3.0  # its own (one line)
        # (more detail)
    return Commented
