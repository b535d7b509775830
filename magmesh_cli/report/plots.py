"""Report figures, one function per figure: ``plot_x(run, ...) -> Figure | None`` (None: no data for it).

matplotlib's object API (``Figure``, no pyplot state), rendered with the Agg backend to PNG.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from magmesh import magcal

from .data import VehicleRun, heading_error, rms

ALARM_COLOURS = {"dmc": "tab:red", "heading": "tab:orange", "heading_innovation": "tab:orange",
                 "track": "tab:purple", "match": "tab:brown", "mag_anomaly": "tab:pink"}
MODE_COLOURS = {"magnetic": "#d8f0d8", "gyro_only": "#f6d5d5", "recovering": "#fbecc8", "initialising": "#e4e4e4"}
DPI = 100


def _fig(rows: int = 1, height: float = 3.0, width: float = 11.0, sharex: bool = True):
    fig = Figure(figsize=(width, height * rows), dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, 1, sharex=sharex, squeeze=False)[:, 0]
    return fig, axes


def shade_alarms(ax, run: VehicleRun, legend: bool = True, truth: bool = True) -> list:
    """Shade alarm intervals (colour per source) and, on a thin band, the truth's disturbed intervals."""
    handles = []
    seen = set()
    for a in run.alarms():
        c = ALARM_COLOURS.get(a.source, "tab:gray")
        ax.axvspan(a.start, a.end, color=c, alpha=0.18, lw=0)
        ax.axvline(a.start, color=c, lw=0.8, alpha=0.7)
        if a.source not in seen:
            seen.add(a.source)
            handles.append(Patch(color=c, alpha=0.3, label=f"alarm: {a.source}"))
    if truth:
        for s, e in run.disturbed_intervals():
            ax.axvspan(s, e, ymin=0.0, ymax=0.04, color="black", alpha=0.6, lw=0)
        if run.disturbed_intervals():
            handles.append(Patch(color="black", alpha=0.6, label="truth: disturbed"))
    return handles


def _legend(ax, extra_handles=()):
    h, _ = ax.get_legend_handles_labels()
    if h or extra_handles:
        ax.legend(handles=list(h) + list(extra_handles), loc="upper right", fontsize=8, framealpha=0.85)


# ---- field strength and features --------------------------------------------------------------


def plot_field(run: VehicleRun) -> Figure | None:
    raw = run.mag_sensors("clean") or run.mag_sensors("raw")
    cal = run.mag_sensors("cal")
    dmc = run.messages("dmc")
    if not raw and not cal:
        return None
    rows = 2 if dmc else 1
    fig, axes = _fig(rows, 3.2)
    ax = axes[0]
    colour = {s: f"C{i}" for i, s in enumerate(sorted(set(raw) | set(cal)))}
    for sensor, (t, b) in raw.items():
        ax.plot(t, np.linalg.norm(b, axis=1) / 1000.0, lw=0.8, color=colour[sensor],
                label=f"|b| sensor {sensor} (uncompensated)")
    for sensor, (t, b) in cal.items():
        ax.plot(t, np.linalg.norm(b, axis=1) / 1000.0, lw=0.8, ls="--", color=colour[sensor], alpha=0.8,
                label=f"|h| sensor {sensor} (calibrated)")
    ax.set_ylabel("field strength, µT")
    ax.set_title(f"{run.vehicle}: magnetic field strength and interference features")
    ax.grid(alpha=0.3)
    _legend(ax, shade_alarms(ax, run))
    if dmc:
        t = np.array([m["t_s"] for m in dmc])
        dm = np.array([m["dm_nt"] for m in dmc], float)
        dh = np.degrees([m["dh_rad"] for m in dmc])
        ax1 = axes[1]
        two = dm.shape[1] > 1 and not np.allclose(dm[:, 1], dm[:, 0]) and np.any(dm[:, 1] != 0)
        for k in range(dm.shape[1] if two else 1):
            ax1.plot(t, dm[:, k], lw=0.8, label=f"Δm compass {k + 1}, nT")
        ax1.set_ylabel("Δm, nT")
        ax1.grid(alpha=0.3)
        ax2 = ax1.twinx()
        ax2.plot(t, dh, lw=0.5, color="0.45", alpha=0.5, label="Δh, deg")
        ax1.set_zorder(ax2.get_zorder() + 1)  # Δm in front of the noisier Δh
        ax1.patch.set_visible(False)
        ax2.set_ylabel("Δh, deg")
        lines = ax1.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
        ax1.legend(handles=lines, loc="upper right", fontsize=8)
        shade_alarms(ax1, run, truth=False)
    axes[-1].set_xlabel("sample time, s")
    return fig


def plot_dmc(run: VehicleRun) -> Figure | None:
    dmc = run.messages("dmc")
    if not dmc:
        return None
    t = np.array([m["t_s"] for m in dmc])
    kc = np.array([m["credibility"] for m in dmc])
    valid = np.array([m["valid"] for m in dmc], bool)
    stage1 = np.array([m["stage1_pass"] for m in dmc], bool)
    impl = sorted({m.get("impl", "?") for m in dmc})
    fig, axes = _fig(1, 3.4)
    ax = axes[0]
    ax.plot(t, kc, lw=0.9, color="tab:blue", label="credibility K_c")
    ax.axhline(0.8, color="tab:blue", ls=":", lw=1, label="K_c = 0.8 (valid above)")
    _band(ax, t, ~valid, 0.96, 1.0, color="tab:red", alpha=0.7)
    _band(ax, t, ~stage1, 0.92, 0.96, color="tab:orange", alpha=0.7)
    extra = [Patch(color="tab:red", alpha=0.7, label="heading not valid"),
             Patch(color="tab:orange", alpha=0.7, label="stage-1 thresholds failed")]
    extra += shade_alarms(ax, run)
    ax.set_ylim(-0.05, 1.1)
    ax.set_ylabel("K_c")
    ax.set_xlabel("sample time, s")
    ax.set_title(f"{run.vehicle}: DMC credibility ({', '.join(impl)}); valid {valid.mean() * 100:.1f}% of epochs")
    ax.grid(alpha=0.3)
    _legend(ax, extra)
    return fig


# ---- heading ----------------------------------------------------------------------------------


def plot_heading(run: VehicleRun) -> Figure | None:
    """Fused heading vs truth on the filter's mode; without a heading stream, the DMC's magnetic heading
    vs truth on its validity."""
    hd = run.messages("heading")
    dmc = run.messages("dmc")
    if not hd and not dmc:
        return None
    fused = bool(hd)
    src = hd if fused else dmc
    t = np.array([m["t_s"] for m in src])
    h = np.degrees([m["heading_rad"] for m in src])
    if fused:
        modes = [m["mode"] for m in hd]
        colours = MODE_COLOURS
    else:
        modes = ["valid" if m["valid"] else "not valid" for m in dmc]
        colours = {"valid": MODE_COLOURS["magnetic"], "not valid": MODE_COLOURS["gyro_only"]}
    pose = [m for m in run.truth("pose") if "heading_rad" in m]
    err = heading_error(run, "heading" if fused else "dmc")
    fig, axes = _fig(2, 3.2)
    ax = axes[0]
    _shade_modes(ax, t, modes, colours)
    if pose:
        ax.plot([m["t_s"] for m in pose], np.degrees([m["heading_rad"] for m in pose]), ".", ms=1.5,
                color="k", alpha=0.6, label="truth")
    if fused:
        ax.plot(t, h, ".", ms=1.5, color="tab:blue", label="heading (fused)")
    if dmc:
        ax.plot([m["t_s"] for m in dmc], np.degrees([m["heading_rad"] for m in dmc]), ".", ms=1, color="tab:green",
                alpha=0.5 if fused else 0.9, label="magnetic heading (DMC)")
    ax.set_ylim(0, 360)
    ax.set_yticks(range(0, 361, 90))
    ax.set_ylabel("heading, deg")
    ax.set_title(f"{run.vehicle}: " + ("heading and its mode" if fused else
                                       "magnetic heading (no fused heading recorded) and its DMC validity"))
    ax.grid(alpha=0.3)
    prefix = "mode" if fused else "DMC"
    mode_handles = [Patch(color=c, label=f"{prefix}: {m}") for m, c in colours.items() if m in set(modes)]
    _legend(ax, mode_handles + shade_alarms(ax, run))
    ax = axes[1]
    _shade_modes(ax, t, modes, colours)
    if err is not None:
        te, e = err
        ed = np.degrees(e)
        ax.plot(te, ed, lw=0.8, color="tab:red", label=f"error vs truth (RMS {math.degrees(rms(e)):.1f}°)")
        lim = max(10.0, float(np.nanpercentile(np.abs(ed), 99)) * 1.2) if len(ed) else 10.0
        ax.set_ylim(-lim, lim)
    if fused:
        sd = np.degrees([m["heading_std_rad"] for m in hd])
        ax.fill_between(t, -3 * sd, 3 * sd, color="tab:blue", alpha=0.15, label="±3σ (filter)")
    shade_alarms(ax, run)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_ylabel("heading error, deg")
    ax.set_xlabel("sample time, s")
    ax.grid(alpha=0.3)
    _legend(ax)
    return fig


def _band(ax, t, mask, y0: float = 0.0, y1: float = 1.0, zorder: float = 0, **kw) -> None:
    """Shade the x ranges where ``mask`` holds (each sample until the next), between axes fractions y0..y1.

    One artist for any number of ranges (an axvspan per range is slow for flickering flags)."""
    t = np.asarray(t, float)
    mask = np.asarray(mask, bool)
    if len(t) == 0 or not mask.any():
        return
    upto_next = mask.copy()
    upto_next[1:] |= mask[:-1]  # a sample's range runs to the next sample
    ax.fill_between(t, y0, y1, where=upto_next, step="post", transform=ax.get_xaxis_transform(), lw=0,
                    zorder=zorder, **kw)


def _shade_modes(ax, t, modes, colours=MODE_COLOURS) -> None:
    modes = np.asarray(modes)
    for m in sorted(set(modes.tolist())):
        _band(ax, t, modes == m, color=colours.get(m, "#eeeeee"))


# ---- calibration ------------------------------------------------------------------------------


def calibration_pairs(run: VehicleRun) -> list[tuple[str, np.ndarray, np.ndarray, dict | None]]:
    """(sensor, uncompensated N×3, compensated N×3, params) per sensor with calibration output."""
    out = []
    before = run.mag_sensors("clean") or run.mag_sensors("raw")
    after = run.mag_sensors("cal")
    params = {}
    for k in run.keys_of("cal", "params"):
        ms = run.by_key[k]
        ok = [m for m in ms if m["status"] in ("ok", "manifest")]
        if ok:
            params[ok[-1]["sensor"]] = ok[-1]
        elif ms:  # no usable fit yet: still tells the model (2-D / 3-D) the calibration works in
            params[ms[-1]["sensor"]] = ms[-1]
    for sensor, (t, b) in before.items():
        p = params.get(sensor)
        if p is not None and p["status"] in ("ok", "manifest"):
            # the final fitted parameters applied to every sample: the figure the papers show
            h = magcal.apply(b, p["offset_nt"], np.array(p["matrix"], float).reshape(3, 3))
        elif sensor in after:
            # no usable parameter message recorded: what the mesh compensated, sample by sample
            t_after, h = after[sensor]
            b = np.stack([np.interp(t_after, t, b[:, k]) for k in range(3)], 1) if len(t) > 1 else b
        else:
            continue
        h = np.asarray(h, float)
        if p is None:
            # no parameter message in the run: a 2-D (horizontal) calibration passes z through unchanged
            p = {"model": "2d" if np.allclose(h[:, 2], b[:, 2], atol=1.0) else "3d", "status": None}
        out.append((sensor, b, h, p))
    return out


def plot_calibration(run: VehicleRun) -> Figure | None:
    pairs = calibration_pairs(run)
    if not pairs:
        return None
    n = len(pairs)
    fig = Figure(figsize=(11, 4.6 * n), dpi=DPI, layout="constrained")
    for row, (sensor, b, h, p) in enumerate(pairs):
        model = (p or {}).get("model", "3d")
        b_u = b / 1000.0
        h_u = h / 1000.0
        if model == "2d":
            ax0 = fig.add_subplot(n, 2, 2 * row + 1)
            ax1 = fig.add_subplot(n, 2, 2 * row + 2)
            ax0.plot(b_u[:, 0], b_u[:, 1], ".", ms=1.5, color="tab:red")
            ax1.plot(h_u[:, 0], h_u[:, 1], ".", ms=1.5, color="tab:green")
            r = (p or {}).get("field_radius_nt", float(np.median(np.hypot(h[:, 0], h[:, 1])))) / 1000.0
            a = np.linspace(0, 2 * math.pi, 361)
            ax1.plot(r * np.cos(a), r * np.sin(a), "k--", lw=0.8, label=f"circle R = {r:.1f} µT")
            for ax, what in ((ax0, "before: ellipse"), (ax1, "after: circle")):
                ax.set_aspect("equal", adjustable="datalim")
                ax.axhline(0, color="k", lw=0.5)
                ax.axvline(0, color="k", lw=0.5)
                ax.set_xlabel("x (forward), µT")
                ax.set_ylabel("y (left), µT")
                ax.grid(alpha=0.3)
                ax.set_title(f"{run.vehicle} sensor {sensor}, horizontal field {what}")
            ax1.legend(fontsize=8)
        else:
            ax0 = fig.add_subplot(n, 2, 2 * row + 1, projection="3d")
            ax1 = fig.add_subplot(n, 2, 2 * row + 2, projection="3d")
            step = max(1, len(b_u) // 3000)
            ax0.scatter(*b_u[::step].T, s=1, color="tab:red")
            ax1.scatter(*h_u[::step].T, s=1, color="tab:green")
            r = (p or {}).get("field_radius_nt", float(np.median(np.linalg.norm(h, axis=1)))) / 1000.0
            u, v = np.mgrid[0:2 * np.pi:24j, 0:np.pi:12j]
            ax1.plot_wireframe(r * np.cos(u) * np.sin(v), r * np.sin(u) * np.sin(v), r * np.cos(v), color="k",
                               lw=0.3, alpha=0.5)
            for ax, what in ((ax0, "before: ellipsoid"), (ax1, "after: sphere")):
                ax.set_box_aspect((1, 1, 1))
                lim = max(np.abs(b_u).max() if ax is ax0 else np.abs(h_u).max(), 1e-6)
                ax.set_xlim(-lim, lim)
                ax.set_ylim(-lim, lim)
                ax.set_zlim(-lim, lim)
                ax.set_xlabel("x, µT")
                ax.set_ylabel("y, µT")
                ax.set_zlabel("z, µT")
                ax.set_title(f"{run.vehicle} sensor {sensor}, {what}")
        spread_b = _spread(np.linalg.norm(b if model == "3d" else b[:, :2], axis=1))
        spread_h = _spread(np.linalg.norm(h if model == "3d" else h[:, :2], axis=1))
        ax0.text2D(0.02, 0.02, f"|b| spread {spread_b:.1f}%", transform=ax0.transAxes, fontsize=8) if model == "3d" \
            else ax0.text(0.02, 0.02, f"|b| spread {spread_b:.1f}%", transform=ax0.transAxes, fontsize=8)
        label = f"|h| spread {spread_h:.1f}%" + (f", {p['method']} rmse {p['rmse_nt']:.0f} nT"
                                                  if p and p.get("rmse_nt") is not None else "")
        ax1.text2D(0.02, 0.02, label, transform=ax1.transAxes, fontsize=8) if model == "3d" \
            else ax1.text(0.02, 0.02, label, transform=ax1.transAxes, fontsize=8)
    return fig


def _spread(r: np.ndarray) -> float:
    """(p95 − p5) / median of a magnitude, %."""
    r = np.asarray(r, float)
    if r.size == 0 or not np.isfinite(r).any():
        return float("nan")
    p5, p50, p95 = np.nanpercentile(r, [5, 50, 95])
    return float((p95 - p5) / p50 * 100.0) if p50 > 0 else float("nan")


# ---- geomagnetic matching ---------------------------------------------------------------------


def correlation_surface(grid, h_nt: np.ndarray, ins_m: np.ndarray, radius_cells: int = 12, demean: bool = False,
                        ordered: bool = True):
    """Hausdorff distance of the measured anomaly sequence against the map strip for every whole-cell
    shift of the INS track within ``radius_cells`` (the pre-match surface of docs/methods.md#geomag).

    ``ordered``: sample i is compared with strip point i only (max |h_i − r_i|, the matcher's default);
    otherwise the paper's set distance. ``demean`` removes both means (when the main field is unknown).
    Returns (shift_x_m, shift_y_m, d_nt 2-D [ix, iy]) or None when the track leaves the map.
    """
    h = np.asarray(h_nt, float)
    if demean:
        h = h - h.mean()
    sx = np.arange(-radius_cells, radius_cells + 1) * grid.dx_m
    sy = np.arange(-radius_cells, radius_cells + 1) * grid.dy_m
    X, Y = np.meshgrid(sx, sy, indexing="ij")
    pts = ins_m[None, None, :, :2] + np.stack([X, Y], -1)[:, :, None, :]
    ij = grid.to_grid(pts.reshape(-1, 2))
    inside = grid.inside(ij)
    if not np.any(inside):
        return None
    vals = np.full(len(ij), np.nan)
    vals[inside] = grid.bilinear(ij[inside, 0], ij[inside, 1])
    strips = vals.reshape(X.shape + (len(h),))
    complete = ~np.isnan(strips).any(axis=-1)
    strips = np.where(complete[..., None], strips, 0.0)
    if demean:
        strips = strips - strips.mean(axis=-1, keepdims=True)
    if ordered:
        dh = np.abs(h - strips).max(axis=-1)
    else:
        d = np.abs(h[None, None, :, None] - strips[..., None, :])
        dh = np.maximum(d.min(axis=-1).max(axis=-1), d.min(axis=-2).max(axis=-1))
    dh[~complete] = np.nan
    return sx, sy, dh


def plot_geomag(run: VehicleRun, grid=None, main_field_nt: float | None = None) -> Figure | None:
    """Fixes on the map, and the correlation surface of the last fix recomputed from the recorded
    sequence (measured total field minus ``main_field_nt``; de-meaned when that is not known)."""
    fixes = run.messages("fix")
    if not fixes:
        return None
    ins = run.messages("clean", "ins") or run.messages("raw", "ins")
    pose = [m for m in run.truth("pose") if "pos_enu_m" in m]
    fig = Figure(figsize=(11, 5.2), dpi=DPI, layout="constrained")
    ax = fig.add_subplot(1, 2, 1)
    if grid is not None:
        x = grid.x0_m + np.arange(grid.shape[0]) * grid.dx_m
        y = grid.y0_m + np.arange(grid.shape[1]) * grid.dy_m
        im = ax.pcolormesh(x, y, grid.values_nt.T, cmap="viridis", shading="auto", alpha=0.85)
        fig.colorbar(im, ax=ax, label="anomaly, nT", shrink=0.8)
    if ins:
        p = np.array([m["pos_enu_m"] for m in ins])
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:orange", lw=1.2, label="INS")
    if pose:
        p = np.array([m["pos_enu_m"] for m in pose])
        ax.plot(p[:, 0], p[:, 1], "-", color="magenta", lw=1.2, label="truth")
    acc = [f for f in fixes if f["accepted"]]
    rej = [f for f in fixes if not f["accepted"] and f["status"] != "pending"]
    if rej:
        p = np.array([f["pos_enu_m"] for f in rej])
        ax.plot(p[:, 0], p[:, 1], "x", color="tab:red", ms=5, label=f"not accepted ({len(rej)})")
    if acc:
        p = np.array([f["pos_enu_m"] for f in acc])
        q = np.array([f["ins_pos_enu_m"] for f in acc])
        ax.plot(p[:, 0], p[:, 1], "o", mfc="none", color="tab:cyan", ms=6, label=f"accepted fixes ({len(acc)})")
        for a, b in zip(q, p, strict=False):
            ax.annotate("", xy=a[:2], xytext=b[:2], arrowprops=dict(arrowstyle="-", color="tab:cyan", lw=0.6))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_title(f"{run.vehicle}: geomagnetic fixes on the map")
    ax.legend(fontsize=8, loc="upper right")
    ax2 = fig.add_subplot(1, 2, 2)
    surf = _last_surface(run, fixes, ins, grid, main_field_nt)
    if surf is not None:
        sx, sy, d = surf
        im = ax2.pcolormesh(sx, sy, d.T, cmap="magma_r", shading="auto")
        fig.colorbar(im, ax=ax2, label="Hausdorff distance, nT", shrink=0.8)
        k = np.unravel_index(np.nanargmin(d), d.shape)
        ax2.plot(sx[k[0]], sy[k[1]], "c*", ms=12, label="minimum")
        ax2.plot(0, 0, "w+", ms=10, label="INS position")
        fix = ([f for f in fixes if f["accepted"]] or fixes)[-1]
        corr = np.subtract(fix["pos_enu_m"], fix["ins_pos_enu_m"])
        ax2.plot(corr[0], corr[1], "o", mfc="none", mec="tab:cyan", ms=14, label="matcher's fix")
        ax2.set_aspect("equal")
        ax2.set_xlabel("shift east, m")
        ax2.set_ylabel("shift north, m")
        ax2.set_title(f"correlation surface of the last fix (t = {_surface_t(fixes):.0f} s)")
        ax2.legend(fontsize=8)
    else:
        t = np.array([f["t_s"] for f in fixes])
        ax2.plot(t, [f["hausdorff_nt"] for f in fixes], ".", label="best Hausdorff distance")
        margin = [f["margin_nt"] if f["margin_nt"] is not None else np.nan for f in fixes]
        ax2.plot(t, margin, ".", label="margin to runner-up")
        ax2.set_xlabel("sample time, s")
        ax2.set_ylabel("nT")
        ax2.set_title("match quality (no map given: no surface)")
        ax2.grid(alpha=0.3)
        ax2.legend(fontsize=8)
    return fig


def _surface_t(fixes) -> float:
    return ([f for f in fixes if f["accepted"]] or fixes)[-1]["t_s"]


def _last_surface(run: VehicleRun, fixes, ins, grid, main_field_nt=None):
    if grid is None or not ins:
        return None
    target = [f for f in fixes if f["accepted"]] or fixes
    fix = target[-1]
    n = int(fix["n_samples"]) or 20
    mags = run.messages("clean", "mag") or run.messages("raw", "mag")
    if not mags:
        return None
    tm = np.array([m["t_s"] for m in mags])
    f = np.array([m.get("f_nt", float(np.linalg.norm(m["b_nt"]))) for m in mags])
    ti = np.array([m["t_s"] for m in ins])
    pi = np.array([m["pos_enu_m"] for m in ins])
    sel = np.flatnonzero(ti <= fix["t_s"] + 1e-9)[-n:]
    if len(sel) < 3:
        return None
    h = np.interp(ti[sel], tm, f) - (main_field_nt or 0.0)
    # wide enough to hold the matcher's correction with a margin of six cells
    corr = np.hypot(*np.subtract(fix["pos_enu_m"], fix["ins_pos_enu_m"])[:2])
    radius = int(min(40, max(12, np.ceil(corr / min(grid.dx_m, grid.dy_m)) + 6)))
    return correlation_surface(grid, h, pi[sel], radius, demean=main_field_nt is None)


# ---- track deviation --------------------------------------------------------------------------


def plot_track(run: VehicleRun, threshold_m: float = 1.0) -> Figure | None:
    tr = run.messages("track")
    if not tr:
        return None
    t = np.array([m["t_s"] for m in tr])
    d = np.array([m["cross_track_m"] for m in tr])
    inn = np.array([np.nan if m["heading_innovation_rad"] is None else m["heading_innovation_rad"] for m in tr])
    fig, axes = _fig(2, 3.0)
    ax = axes[0]
    ax.plot(t, d, lw=1, label="cross-track deviation d")
    ax.axhline(threshold_m, color="tab:purple", ls="--", lw=1, label=f"d = {threshold_m:g} m")
    extra = shade_alarms(ax, run)
    for a in run.alarms():
        ax.annotate(f"{a.source} {a.start:.1f} s", (a.start, ax.get_ylim()[1]), fontsize=7, rotation=90,
                    va="top", ha="right", color=ALARM_COLOURS.get(a.source, "gray"))
    ax.set_ylabel("m")
    ax.set_title(f"{run.vehicle}: track deviation and heading innovation with alarm times")
    ax.grid(alpha=0.3)
    _legend(ax, extra)
    ax = axes[1]
    ax.plot(t, np.degrees(inn), lw=0.8, color="tab:orange", label="heading innovation (mag − attitude)")
    sig = [m["innovation_sigma_rad"] for m in tr if m.get("innovation_sigma_rad") is not None]
    if sig:
        s5 = 5 * math.degrees(sig[-1])
        ax.axhline(s5, color="tab:orange", ls="--", lw=0.8, label="±5σ")
        ax.axhline(-s5, color="tab:orange", ls="--", lw=0.8)
    shade_alarms(ax, run, truth=False)
    ax.set_ylabel("deg")
    ax.set_xlabel("sample time, s")
    ax.grid(alpha=0.3)
    _legend(ax)
    return fig


def plot_track_map(run: VehicleRun) -> Figure | None:
    routes = run.messages("clean", "route") or run.messages("raw", "route")
    pose = [m for m in run.truth("pose") if "pos_enu_m" in m]
    gnss = run.messages("clean", "gnss") or run.messages("raw", "gnss")
    if not routes or not (pose or gnss):
        return None
    fig, axes = _fig(1, 4.5, 7.0)
    ax = axes[0]
    for r in routes[-1:]:
        a, b = np.array(r["a_enu_m"]), np.array(r["b_enu_m"])
        ax.plot([a[0], b[0]], [a[1], b[1]], "k--", lw=1, label=f"route {r['route_id']}")
    if gnss:
        p = np.array([m["pos_enu_m"] for m in gnss if "pos_enu_m" in m])
        if len(p):
            ax.plot(p[:, 0], p[:, 1], "-", lw=1, color="tab:blue", label="GNSS")
    if pose:
        p = np.array([m["pos_enu_m"] for m in pose])
        ax.plot(p[:, 0], p[:, 1], "-", lw=0.8, color="k", alpha=0.5, label="truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_title(f"{run.vehicle}: flown track vs planned line")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def plot_timeline(runs: dict[str, VehicleRun]) -> Figure | None:
    """Alarms of every vehicle on one time axis."""
    if not any(r.alarms() for r in runs.values()):
        return None
    names = list(runs)
    fig, axes = _fig(1, max(2.0, 0.5 * len(names) + 1.2))
    ax = axes[0]
    for i, name in enumerate(names):
        for a in runs[name].alarms():
            ax.barh(i, a.end - a.start, left=a.start, height=0.6, color=ALARM_COLOURS.get(a.source, "gray"),
                    alpha=0.7)
            ax.text(a.start, i + 0.35, a.source, fontsize=7)
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("sample time, s")
    ax.set_title("alarms per vehicle")
    ax.grid(alpha=0.3, axis="x")
    return fig
