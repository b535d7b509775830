"""Run reports: PNG plots and an HTML page with a summary table, from recorded magmesh messages.

    from magmesh_cli.report import build_report
    index = build_report(messages, "report/", title="drive 2026-06-01")   # messages: [(key, msg), ...]

Figures per vehicle (each only when its streams are present): field strength and DMC features with
alarms shaded, DMC credibility K_c, heading vs truth and its error with the mode, calibration
before/after (ellipse → circle, ellipsoid → sphere), geomagnetic fixes on the map with the correlation
surface, track deviation with alarm times; plus an alarm timeline of all vehicles. Pure: matplotlib
(Agg) and numpy, no Zenoh.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
from collections.abc import Iterable, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

from . import plots  # noqa: E402
from .data import VehicleRun, group  # noqa: E402
from .summary import summary_rows, vehicle_summary  # noqa: E402

FIGURES = (
    ("field", "Field strength and interference features", plots.plot_field),
    ("dmc", "DMC credibility", plots.plot_dmc),
    ("heading", "Heading vs truth", plots.plot_heading),
    ("calibration", "Calibration before / after", plots.plot_calibration),
    ("geomag", "Geomagnetic matching", None),  # needs the map: see _render
    ("track", "Track deviation", plots.plot_track),
    ("track_map", "Track vs planned line", plots.plot_track_map),
)


def build_report(
    messages: Iterable[tuple[str, dict]],
    out_dir: str | Path,
    title: str = "magmesh run",
    source: str = "",
    liveliness: Sequence[tuple[float, str, bool]] = (),
    grid=None,
    grids: dict | None = None,
    main_field_nt: dict | None = None,
    vehicles: Sequence[str] | None = None,
    progress: bool = False,
    notes: Sequence[str] = (),
) -> Path:
    """Write ``index.html``, the PNGs and ``summary.json`` into ``out_dir``; return the HTML path.

    ``grid`` is the anomaly map drawn under geomagnetic fixes; ``grids`` maps a vehicle id to its own map,
    ``main_field_nt`` a vehicle id to the core field its matcher subtracts (else sequences are de-meaned).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = group(messages)
    if vehicles:
        runs = {v: r for v, r in runs.items() if v in set(vehicles)}
    jobs = [(v, name, label, fn) for v in runs for name, label, fn in FIGURES]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs) + 1, unit="fig", desc="report")
    images: dict[str, list[tuple[str, str]]] = {v: [] for v in runs}
    for v, name, label, fn in jobs:
        run = runs[v]
        fig = plots.plot_geomag(run, (grids or {}).get(v, grid), (main_field_nt or {}).get(v)) if name == "geomag" else fn(run)
        if fig is not None:
            fname = f"{_safe(v)}_{name}.png"
            fig.savefig(out / fname)
            images[v].append((label, fname))
        if bar is not None:
            bar.update(1)
    timeline = plots.plot_timeline(runs)
    if timeline is not None:
        timeline.savefig(out / "timeline.png")
    if bar is not None:
        bar.update(1)
        bar.close()
    summaries = {v: vehicle_summary(r) for v, r in runs.items()}
    (out / "summary.json").write_text(json.dumps({"title": title, "source": source, "vehicles": summaries},
                                                 indent=1, default=_json_default))
    page = _html(title, source, runs, summaries, images, timeline is not None, liveliness, notes)
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    return index


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _safe(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in s)


_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1150px; color: #222; }
h1 { margin-bottom: 0.1em; } .sub { color: #666; margin-top: 0; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em; font-size: 0.92em; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; } td.k { color: #444; white-space: nowrap; }
figure { margin: 0.8em 0 1.6em; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #555; font-size: 0.9em; } nav a { margin-right: 1em; }
.raised { color: #b00; } .cleared { color: #070; }
"""


def _html(title, source, runs: dict[str, VehicleRun], summaries, images, has_timeline, liveliness, notes) -> str:
    e = html.escape
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(title)}</title>",
             f"<style>{_CSS}</style></head><body>",
             f"<h1>{e(title)}</h1><p class='sub'>{e(source)} — report made {now}</p>"]
    for n in notes:
        parts.append(f"<p>{e(n)}</p>")
    if not runs:
        parts.append("<p><b>No vehicle messages in this run.</b></p>")
    parts.append("<nav>" + "".join(f"<a href='#{_safe(v)}'>{e(v)}</a>" for v in runs) + "</nav>")
    # overview table
    parts.append("<h2>Summary</h2><table><tr><th>vehicle</th><th>span, s</th><th>messages</th><th>alarms</th>"
                 "<th>heading RMS vs truth</th><th>rejects</th></tr>")
    for v, s in summaries.items():
        h = s["heading"] or {}
        d = s["dmc"] or {}
        hr = (f"{h['rms_deg']:.2f}°" if h.get("rms_deg") is not None else
              f"DMC {d['all_rms_deg']:.2f}°" if d.get("all_rms_deg") is not None else "–")
        al = ", ".join(f"{k} ×{n}" for k, n in s["alarms"].items()) or "none"
        parts.append(f"<tr><td><a href='#{_safe(v)}'>{e(v)}</a></td><td>{s['duration_s']:.1f}</td>"
                     f"<td>{s['messages']}</td><td>{e(al)}</td><td>{hr}</td><td>{s['rejects']}</td></tr>")
    parts.append("</table>")
    if has_timeline:
        parts.append("<figure><img src='timeline.png' alt='alarm timeline'><figcaption>Alarms of every vehicle "
                     "(sample time).</figcaption></figure>")
    if liveliness:
        parts.append("<h2>Services</h2><table><tr><th>time (UTC)</th><th>service</th><th>event</th></tr>")
        for t, token, alive in liveliness:
            ts = _dt.datetime.fromtimestamp(t, _dt.UTC).strftime("%H:%M:%S.%f")[:-3]
            cls, word = ("cleared", "appeared") if alive else ("raised", "gone")
            parts.append(f"<tr><td>{ts}</td><td>{e(token)}</td><td class='{cls}'>{word}</td></tr>")
        parts.append("</table>")
    for v, run in runs.items():
        s = summaries[v]
        parts.append(f"<h2 id='{_safe(v)}'>{e(v)}</h2><table>")
        for k, val in summary_rows(s):
            parts.append(f"<tr><td class='k'>{e(k)}</td><td>{e(val)}</td></tr>")
        parts.append("</table>")
        alarms = run.alarms()
        if alarms:
            parts.append("<table><tr><th>source</th><th>raised, s</th><th>cleared, s</th><th>severity</th>"
                         "<th>reason</th></tr>")
            for a in alarms[:200]:
                cleared = f"{a.end:.2f}" if a.cleared else "(still raised)"
                parts.append(f"<tr><td>{e(a.source)}</td><td>{a.start:.2f}</td><td>{cleared}</td>"
                             f"<td>{e(a.severity)}</td><td>{e(a.reason)}</td></tr>")
            if len(alarms) > 200:
                parts.append(f"<tr><td colspan='5'>… {len(alarms) - 200} more</td></tr>")
            parts.append("</table>")
        for label, fname in images[v]:
            parts.append(f"<figure><img src='{e(fname)}' alt='{e(label)}'><figcaption>{e(label)}</figcaption>"
                         "</figure>")
        if not images[v]:
            parts.append("<p>No plottable streams for this vehicle.</p>")
    parts.append("</body></html>")
    return "\n".join(parts)
