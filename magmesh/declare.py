"""What a service declares — its settings, inputs and outputs — written once and read by the runtime.

A service's ``Settings`` stays a frozen dataclass whose fields are made with :func:`setting`: the default plus a
description, a unit (units stay in the names too: the unit is what the name's suffix says unless given) and the
allowed values (a range ``lo``/``hi`` inclusive or ``gt``/``lt`` strict, or ``choices``), PX4-style. ``INPUTS`` lists
the streams the service takes (:class:`Input`: a key template of the streams table, ``schemas/streams.py``) and
``OUTPUTS`` the ones it publishes (:class:`Output`). The runtime derives from them what used to be written by hand:

- the subscriptions (:func:`subscriptions`: each input's key built by its ``schemas.keys`` builder for the
  instance's vehicle pattern and the sensors its settings name);
- ``consumes`` / ``produces`` of the status reply and of ``--help`` (:func:`consumes`, :func:`produces`,
  :func:`streams_help`);
- the settings table of ``--help`` (:func:`settings_table`) and the check of every value given to a setting
  (:func:`check_values`: a bad value is one :class:`SettingError` naming setting, value and what is allowed).

A Settings class written without :func:`setting` (the heading filter's ``core.Settings``) is described by its
source comments: a field's trailing comment, else the comment block above it. Pure: no zenoh.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import math
import string
import textwrap
import tokenize
from collections.abc import Callable, Iterable
from functools import cache
from typing import Any

from schemas import keys, streams

# ---- settings ---------------------------------------------------------------------------------------------------

#: the unit a name's suffix stands for (longest suffix first)
SUFFIX_UNITS: tuple[tuple[str, str], ...] = tuple(sorted({
    "_rad_s2_rt_hz": "rad/s²/√Hz", "_rad_s_rt_hz": "rad/s/√Hz", "_frac_rt_hz": "1/√Hz",
    "_m_s2_per_rad_s": "(m/s²)/(rad/s)", "_nt_sqrt_s": "nT/√s", "_m_sqrt_s": "m/√s", "_per_s": "1/s",
    "_nt_s": "nT/s", "_deg_s": "deg/s", "_rad_s2": "rad/s²", "_rad_s": "rad/s", "_m_s2": "m/s²", "_m_s": "m/s",
    "_g_s": "G/s", "_nt2": "nT²", "_rad2": "rad²", "_m2": "m²", "_nt": "nT", "_deg": "deg", "_rad": "rad",
    "_hz": "Hz", "_m": "m", "_s": "s", "_g": "G", "_frac": "fraction", "_samples": "samples", "_sigma": "σ",
}.items(), key=lambda kv: -len(kv[0])))


def unit_of(name: str) -> str:
    """The unit a setting's name carries in its suffix (``pair_tolerance_s`` → ``s``), or ``""``."""
    for suffix, unit in SUFFIX_UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def setting(default: Any, doc: str, *, unit: str | None = None, lo: float | None = None, hi: float | None = None,
            gt: float | None = None, lt: float | None = None, choices: Iterable | None = None) -> Any:
    """A field of a Settings dataclass: its default, what it means (``doc``), its unit (default: the name's
    suffix, :func:`unit_of`) and the values it allows: ``lo`` ≤ v ≤ ``hi``, ``gt`` < v < ``lt`` (either bound may be
    left out), or one of ``choices`` (for a tuple, each element). A dict or list default is copied per instance."""
    if not doc or not doc.strip():
        raise ValueError("a setting needs a description")
    md = {"doc": " ".join(doc.split()), "unit": unit, "lo": lo, "hi": hi, "gt": gt, "lt": lt,
          "choices": tuple(choices) if choices is not None else None}
    if isinstance(default, (dict, list, set)):
        return dataclasses.field(default_factory=lambda d=default: type(d)(d), metadata=md)
    return dataclasses.field(default=default, metadata=md)


class SettingError(ValueError):
    """A value a setting does not allow: names the setting, the value and what is allowed (one sentence)."""

    def __init__(self, name: str, value: Any, problem: str, allowed: str = ""):
        self.name, self.value, self.problem, self.allowed = name, value, problem, allowed
        text = f"setting {name} {value!r} {problem}"
        super().__init__(f"{text}: allowed {allowed}" if allowed else text)


@dataclasses.dataclass(frozen=True)
class SettingInfo:
    """One setting as ``--help`` shows it and :func:`check_values` checks it."""

    name: str
    type: str
    default: Any
    doc: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    gt: float | None = None
    lt: float | None = None
    choices: tuple | None = None

    @property
    def allowed(self) -> str:
        """What the setting allows, in words: ``> 0``, ``[0, 1]``, ``(0, 5]``, ``arls | ls`` (``""``: not declared)."""
        if self.choices is not None:
            return " | ".join('""' if c == "" else str(c) for c in self.choices)
        low = (f"[{_num(self.lo)}" if self.lo is not None else f"({_num(self.gt)}") \
            if self.lo is not None or self.gt is not None else None
        high = (f"{_num(self.hi)}]" if self.hi is not None else f"{_num(self.lt)})") \
            if self.hi is not None or self.lt is not None else None
        if low and high:
            return f"{low}, {high}"
        if low:
            return f"≥ {_num(self.lo)}" if self.lo is not None else f"> {_num(self.gt)}"
        if high:
            return f"≤ {_num(self.hi)}" if self.hi is not None else f"< {_num(self.lt)}"
        return ""

    def check(self, value: Any) -> None:
        """Raise :class:`SettingError` when ``value`` is not one this setting allows."""
        if self.choices is not None:
            items = value if isinstance(value, (tuple, list)) and self.type.startswith(("tuple", "list")) else (value,)
            bad = [x for x in items if x not in self.choices]
            if bad:
                raise SettingError(self.name, value, "is unknown" if len(items) == 1 else
                                   f"names {', '.join(map(repr, bad))}, unknown", self.allowed)
            return
        if all(b is None for b in (self.lo, self.hi, self.gt, self.lt)):
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingError(self.name, value, "is not a number", self.allowed)
        v = float(value)
        ok = not math.isnan(v) and (self.lo is None or v >= self.lo) and (self.hi is None or v <= self.hi) and \
            (self.gt is None or v > self.gt) and (self.lt is None or v < self.lt)
        if not ok:
            raise SettingError(self.name, value, "is out of range",
                               f"{self.allowed} {self.unit}".rstrip() if self.unit not in ("", "fraction") else
                               self.allowed)


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def type_name(tp: Any) -> str:
    s = tp if isinstance(tp, str) else getattr(tp, "__name__", str(tp))
    return s.replace("typing.", "")


@cache
def settings_info(cls: type | None) -> tuple[SettingInfo, ...]:
    """Every setting of a Settings dataclass, in field order (``()`` for None)."""
    if cls is None:
        return ()
    comments = None
    out = []
    for f in dataclasses.fields(cls):
        md = f.metadata or {}
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        doc = md.get("doc")
        if doc is None:
            if comments is None:
                comments = comment_docs(cls)
            doc = comments.get(f.name, "")
        unit = md.get("unit")
        out.append(SettingInfo(f.name, type_name(f.type), default, doc, unit_of(f.name) if unit is None else unit,
                               md.get("lo"), md.get("hi"), md.get("gt"), md.get("lt"), md.get("choices")))
    return tuple(out)


def check_values(cls: type | None, values: dict) -> None:
    """Check given setting values against what their declarations allow (:class:`SettingError` on the first bad
    one); names the class does not have are left to the caller."""
    by_name = {s.name: s for s in settings_info(cls)}
    for name, value in values.items():
        info = by_name.get(name)
        if info is not None:
            info.check(value)


def check(settings: Any) -> None:
    """Check every value of a Settings instance against its declarations (for ``__post_init__``: a Settings built
    in code is held to the same ranges as one built from ``--set``)."""
    for info in settings_info(type(settings)):
        info.check(getattr(settings, info.name))


def settings_table(cls: type | None, width: int = 118) -> str:
    """The settings of ``--help``: name, type, unit, default, allowed range and description, one row each."""
    rows = settings_info(cls)
    if not rows:
        return "  (none)"
    cells = [(s.name, s.type, s.unit, _default_text(s.default), s.allowed, s.doc) for s in rows]
    head = ("name", "type", "unit", "default", "range", "description")
    w = [max(len(r[i]) for r in [*cells, head]) for i in range(5)]
    w[3], w[4] = min(w[3], 12), min(w[4], 16)
    lead = sum(w) + 2 * 5 + 2
    lines = ["  " + "  ".join(h.ljust(w[i]) for i, h in enumerate(head[:5])) + "  " + head[5]]
    for r in cells:
        left = "  " + "  ".join(r[i].ljust(w[i]) for i in range(5)) + "  "
        if len(left) > lead:  # a long default or range: the description starts on the next line
            lines.append(left.rstrip())
            left = " " * lead
        wrapped = textwrap.wrap(r[5], max(30, width - lead), break_on_hyphens=False) or [""]
        lines.append(left + wrapped[0])
        lines += [" " * lead + x for x in wrapped[1:]]
    return "\n".join(lines)


def _default_text(v: Any) -> str:
    if isinstance(v, str):
        return repr(v)
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


# ---- descriptions from source comments (Settings classes written without setting()) -------------------------------


def comment_docs(cls: type) -> dict[str, str]:
    """Each field's description from the class's source: its trailing comment (with the lines that continue it
    while a parenthesis stays open or that start with "("), else the comment block right above it, else
    the block above its group. Base classes first, so a subclass's own comment wins."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object or not dataclasses.is_dataclass(klass) or "__dataclass_fields__" not in vars(klass):
            continue
        try:
            src = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        out.update(_class_comments(src))
    return out


def _class_comments(src: str) -> dict[str, str]:
    own: dict[int, str] = {}  # line → text of a comment alone on its line
    trailing: dict[int, str] = {}  # line → text of a comment after code
    code_lines: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            (trailing if tok.start[0] in code_lines else own)[tok.start[0]] = text
        elif tok.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER):
            code_lines.update(range(tok.start[0], tok.end[0] + 1))
    body = ast.parse(src).body[0].body
    out: dict[str, str] = {}
    block, prev_end, prev_trailing, prev_name = "", 0, "", ""
    for node in [*body, None]:  # (None: the comments after the last statement)
        start = node.lineno if node is not None else max(own, default=0) + 1
        between = [ln for ln in sorted(own) if prev_end < ln < start]
        cont: list[int] = []  # lines continuing the previous field's trailing comment
        text = prev_trailing
        for ln in between:
            if not prev_trailing or ln != prev_end + 1 + len(cont):
                break
            if not (_open_parens(text) > 0 or own[ln].startswith("(")):
                break
            cont.append(ln)
            text += " " + own[ln]
        if cont:
            out[prev_name] = text
        rest = [ln for ln in between if ln not in cont]
        if rest:
            run = [rest[-1]]
            for ln in reversed(rest[:-1]):  # the contiguous comment lines right above
                if ln != run[0] - 1:
                    break
                run.insert(0, ln)
            block = " ".join(own[ln] for ln in run)
        prev_trailing = ""
        if node is None:
            break
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            t = trailing.get(node.end_lineno) or trailing.get(node.lineno) or ""
            out[node.target.id] = t or block
            prev_trailing, prev_name = t, node.target.id
        prev_end = node.end_lineno
    return out


def _open_parens(text: str) -> int:
    return text.count("(") - text.count(")")


# ---- inputs and outputs -------------------------------------------------------------------------------------------

#: key templates beyond the streams table's rows: a kind's every stream (ingest takes raw/**) and the batches
EXTRA_TEMPLATES: dict[str, Callable[..., str]] = {
    f"{keys.ROOT}/{{vehicle}}/raw/**": keys.raw_all,
    f"{keys.ROOT}/{{vehicle}}/clean/**": keys.clean_all,
    f"{keys.ROOT}/{{vehicle}}/raw/{keys.BATCH}": keys.raw_batch,
    f"{keys.ROOT}/{{vehicle}}/clean/{keys.BATCH}": keys.clean_batch,
}


@cache
def _builders() -> dict[str, Callable[..., str]]:
    out = {st.template: st.builder for st in streams.STREAMS.values()}
    out.update(EXTRA_TEMPLATES)
    return out


def _placeholders(template: str) -> tuple[str, ...]:
    return tuple(f for _, f, _, _ in string.Formatter().parse(template) if f)


def _check_template(template: str, what: str) -> None:
    if template not in _builders():
        raise ValueError(f"{what} {template!r} is not a key template of the streams table (schemas/streams.py); "
                         f"known: {', '.join(sorted(_builders()))}")


def _value(settings: Any, name: str, declared: type | None) -> Any:
    """A setting's value; one the instance's settings lack (a test's narrower Settings) is the declared default."""
    v = getattr(settings, name, _MISSING)
    if v is _MISSING:
        v = next((s.default for s in settings_info(declared) if s.name == name), None)
    return v


_MISSING = object()


def _when_active(when: Any, settings: Any, declared: type | None = None) -> bool:
    if when is None:
        return True
    if isinstance(when, str):
        return bool(_value(settings, when, declared))
    name, value = when
    v = _value(settings, name, declared)
    return v in value if isinstance(value, (tuple, list, set, frozenset)) else v == value


def _when_text(when: Any) -> str:
    if when is None:
        return ""
    if isinstance(when, str):
        return f"when {when} is on"
    name, value = when
    if isinstance(value, (tuple, list, set, frozenset)):
        return f"when {name} is {' or '.join(map(str, value))}"
    return f"when {name} = {value}"


def short(template: str, **fixed: str | None) -> str:
    """A template as status and ``--help`` show it: without ``magmesh/{vehicle}/``, fixed parts filled in."""
    prefix = f"{keys.ROOT}/{{vehicle}}/"
    s = template[len(prefix):] if template.startswith(prefix) else template
    for k, v in fixed.items():
        if v is not None:
            s = s.replace("{" + k + "}", v)
    return s


@dataclasses.dataclass(frozen=True)
class Input:
    """A stream the service takes: ``template`` (a key template of the streams table), what it is used for, the
    sensors (``{sensor}``: ``"*"`` for every one, or the setting(s) naming them; a setting left empty names none)
    and ``when`` it is taken (``None``: always; a setting's name: while it is on; ``(setting, value)``: while it
    has that value, or one of a tuple of values)."""

    template: str
    doc: str
    sensors: str | tuple[str, ...] | None = None
    when: str | tuple | None = None

    def __post_init__(self) -> None:
        _check_template(self.template, "input")
        has = "sensor" in _placeholders(self.template)
        if has != (self.sensors is not None):
            raise ValueError(f"input {self.template!r}: sensors= is needed exactly when the template has {{sensor}}")
        extra = set(_placeholders(self.template)) - {"vehicle", "sensor"}
        if extra:
            raise ValueError(f"input {self.template!r}: cannot subscribe with {', '.join(sorted(extra))} unfilled")

    @property
    def short(self) -> str:
        return short(self.template)

    def sensor_ids(self, settings: Any, declared: type | None = None) -> list[str]:
        """The sensors this input names under ``settings`` (``["*"]`` for every one)."""
        if self.sensors is None:
            return []
        if self.sensors == "*":
            return ["*"]
        out: list[str] = []
        for name in (self.sensors,) if isinstance(self.sensors, str) else self.sensors:
            v = _value(settings, name, declared)
            if isinstance(v, str):
                if v:
                    out.append(v)
            else:
                out.extend(str(x) for x in v)
        return out

    def keys(self, vehicle_pattern: str, settings: Any, declared: type | None = None) -> list[str]:
        """The key expressions of this input (none while ``when`` is off), built by the streams table's builder
        (``declared``: the service's Settings class, whose defaults stand in for settings an instance lacks)."""
        if not _when_active(self.when, settings, declared):
            return []
        build = _builders()[self.template]
        if self.sensors is None:
            return [build(vehicle_pattern)]
        return [build(vehicle_pattern, s) for s in self.sensor_ids(settings, declared)]

    def help_line(self) -> str:
        notes = []
        if self.sensors is not None and self.sensors != "*":
            names = (self.sensors,) if isinstance(self.sensors, str) else self.sensors
            notes.append(f"{{sensor}}: setting {', '.join(names)}")
        if self.when is not None:
            notes.append(_when_text(self.when))
        return self.doc + (f" ({'; '.join(notes)})" if notes else "")


@dataclasses.dataclass(frozen=True)
class Output:
    """A stream the service publishes: ``template`` (a key template of the streams table), what it carries, the
    fixed parts of its key (``source`` of an alarm, ``what`` of a truth stream) and ``when`` (as for :class:`Input`)."""

    template: str
    doc: str
    source: str | None = None
    what: str | None = None
    when: str | tuple | None = None

    def __post_init__(self) -> None:
        _check_template(self.template, "output")
        for part in ("source", "what"):
            if (getattr(self, part) is not None) != (part in _placeholders(self.template)):
                raise ValueError(f"output {self.template!r}: {part}= is needed exactly when the template has {{{part}}}")

    @property
    def short(self) -> str:
        return short(self.template, source=self.source, what=self.what)

    def help_line(self) -> str:
        return self.doc + (f" ({_when_text(self.when)})" if self.when is not None else "")


def alarm(source: str, doc: str, when: str | tuple | None = None) -> Output:
    """The output of an alarm: ``magmesh/{vehicle}/alarm/{source}`` (its hysteresis in ``doc``)."""
    return Output(streams.STREAMS["alarm"].template, doc, source=source, when=when)


def subscriptions(svc: Any) -> list[str]:
    """The key expressions a service subscribes to: every active input's keys, in declaration order."""
    out: list[str] = []
    cls = type(svc)
    for i in cls.INPUTS:
        out += i.keys(svc.vehicle_pattern, svc.settings, cls.Settings)
    return out


def _listing(decls: Iterable, obj: Any) -> list[str]:
    if isinstance(obj, type):
        return [d.short for d in decls]
    return [d.short for d in decls if _when_active(d.when, obj.settings, type(obj).Settings)]


def consumes(obj: Any) -> list[str]:
    """The inputs (short templates) of a service class, or the active ones of an instance (status)."""
    cls = obj if isinstance(obj, type) else type(obj)
    return _listing(cls.INPUTS, obj)


def produces(obj: Any) -> list[str]:
    """The outputs (short templates) of a service class, or the active ones of an instance (status)."""
    cls = obj if isinstance(obj, type) else type(obj)
    return _listing(cls.OUTPUTS, obj)


def streams_help(cls: type, width: int = 118) -> str:
    """``consumes`` and ``produces`` of ``--help``: each stream with what it is for."""
    parts = []
    for title, decls in (("consumes", cls.INPUTS), ("produces", cls.OUTPUTS)):
        if not decls:
            parts.append(f"{title}: -")
            continue
        w = min(34, max(len(d.short) for d in decls))
        lines = [f"{title}:"]
        for d in decls:
            lead = f"  {d.short.ljust(w)}  "
            wrapped = textwrap.wrap(d.help_line(), max(30, width - max(len(lead), w + 4)),
                                    break_on_hyphens=False) or [""]
            if len(lead) > w + 4:
                lines.append(lead.rstrip())
                lead = " " * (w + 4)
            lines.append(lead + wrapped[0])
            lines += [" " * len(lead) + x for x in wrapped[1:]]
        parts.append("\n".join(lines))
    return "\n".join(parts) + f"\n(keys without a {keys.ROOT}/ prefix are {keys.ROOT}/{{vehicle}}/...)"
