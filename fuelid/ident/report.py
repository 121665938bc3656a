"""The diagnosis report (issue #7): one self-contained HTML file that works offline.

`render_report(model, ds, ...)` returns the page, `write_report(path, model, ds, ...)` writes it; `fuelid report`
and the fleet service call them. The page shows, for a model on a dataset (ident.dataset.Dataset):

- a header: truck, data files, time range, model structure and orders, generation time, fuelid version;
- the verdict and the ranked candidate effects with their evidence (ident.diagnosis.diagnose's dict, consumed by
  its documented keys);
- measured fuel vs the model's simulation and 1-step prediction over time, with zoom and pan;
- the simulation error ŷ_sim − y with the worst stretches marked and labelled by their driving context;
- the whiteness plots with the paper's 99 % bounds (Fig. 7 of seed paper 000): r_e(h) and r_eu(h);
- the error over the engine speed × torque plane (bias and RMS heat maps);
- for an engine model (ident.hammerstein), its identified steady-state map over speed × torque where the
  identification data cover it, beside the true map when the data come from the simulator with a VECTO engine;
- with AFTER models (the same data, effects added): their metrics side by side, their curves overlaid, and
  "RMS error fell from X to Y L/h; cycle fuel error from A % to B %".

Charts: plotly.js, inlined once in <head> from the `plotly` PyPI package (MIT licence; the minified bundle is
about 4.8 MB, so a report is about 5 MB, 1.5 MB gzipped). It is chosen because it does heat maps, bars, zoom,
pan and hover out of the box and comes as one pip dependency with no JavaScript build step; the figures are
built as plotly figure dicts, validated by plotly.graph_objects and embedded by plotly.io.to_html. Nothing on
the page is fetched: no src/href points outside the file (the plotly logo link is switched off).

Long series are min/max decimated (`minmax_decimate`) so the browser stays fast: a series with more samples
than the point budget keeps, per bucket of consecutive samples, its smallest and largest value in time order,
so peaks and the envelope survive at any zoom, while detail finer than a bucket is lost (the page says so).
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import html
import math
from pathlib import Path

import numpy as np

from fuelid import __version__
from fuelid.ident.diagnosis import Diagnosis, diagnose
from fuelid.ident.hammerstein import engine_map_of, steady_state_map
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.validation import WHITENESS_MEANING, autocorr_test, crosscorr_test, metrics
from fuelid.logger.decode import signal_units

MAX_POINTS = 6000  # points per time-series trace after decimation
PLOTLY_CONFIG = {"displaylogo": False, "responsive": True}
COLOURS = ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf")  # before, after 1, after 2, …
MEASURED = "#222222"


# ---- plain functions over arrays -------------------------------------------------------------------------

def minmax_decimate(x: np.ndarray, y: np.ndarray, max_points: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Min/max decimation of the curve (x, y) to at most about max_points points, gaps kept.

    Each run of finite y is cut into b buckets of k = ⌈L/b⌉ consecutive samples, b = ⌊P_run/2⌋ with the run's
    share P_run = max_points · L / N of the budget (N finite samples in all, L in the run); per bucket the
    samples argmin y and argmax y are kept in time order. Runs that fit their budget are kept whole. Runs are
    joined with a NaN point (a break in a plotted line)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(y)
    total = int(ok.sum())
    if total <= max_points:
        return x, y
    edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
    xs, ys = [], []
    for a, b in zip(edges[::2], edges[1::2]):
        L = b - a
        buckets = max(int(max_points * L / total) // 2, 1)
        if L <= 2 * buckets:
            idx = np.arange(a, b)
        else:
            k = math.ceil(L / buckets)
            buckets = math.ceil(L / k)  # so that the last bucket holds a sample
            pad = np.full(buckets * k - L, np.nan)
            blocks = np.r_[y[a:b], pad].reshape(buckets, k)
            base = a + k * np.arange(buckets)
            lo, hi = base + np.nanargmin(blocks, axis=1), base + np.nanargmax(blocks, axis=1)
            idx = np.unique(np.r_[lo, hi])  # sorted: each bucket's two samples in time order
        xs += [x[idx], [np.nan]]
        ys += [y[idx], [np.nan]]
    return np.concatenate(xs[:-1]), np.concatenate(ys[:-1])


def pretty_unit(unit: str) -> str:
    """Units as an engineer writes them: Nm → N·m."""
    return {"Nm": "N·m"}.get(unit, unit)


def _fmt(v, spec: str, none: str = "–") -> str:
    return none if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _esc(v) -> str:
    return html.escape(str(v), quote=True)


def _name(v) -> str:
    """An escaped bus-signal or effect name that may break after its '.' and ':' (DBC names have no spaces)."""
    return _esc(v).replace(".", ".<wbr>").replace(":", ":<wbr>")


# ---- model runs ------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Curve:
    """One model on the data: its label, colour, run (ident.modelrun.ModelRun: simulation, 1-step prediction,
    prediction errors on the grid; drawn on the segments the diagnosis tests) and validation metrics
    (ident.validation.metrics plus the unit)."""

    label: str
    colour: str
    model: object
    run: ModelRun
    metrics: dict


def tested_run(model, ds) -> ModelRun:
    """The ModelRun of `model` on ds; ValueError when it has no segment the diagnosis could test."""
    run = run_model(model, ds)
    run.require_tested()
    return run


def structure_text(model) -> str:
    """'Box-Jenkins; EEC1.EngSpeed [rpm] nb=4 nf=5 nk=3, …; nc=11 nd=11; Ts 0.3 s; effects: …'."""
    s = model.structure
    kind = {"bj": "Box-Jenkins", "oe": "output-error", "arx": "ARX", "armax": "ARMAX"}.get(s.kind, s.kind)
    inputs = ", ".join(f"{n} [{pretty_unit(u)}] nb={nb} nf={nf} nk={nk}"
                       for n, u, nb, nf, nk in zip(model.input_names, model.input_units, s.nb, s.nf, s.nk))
    noise = f"na={s.na} nc={s.nc} nd={s.nd}" if s.na else f"nc={s.nc} nd={s.nd}"
    effects = ", ".join(model.effects) or "none"
    return (f"{kind}; {inputs}; {noise}; Ts {model.Ts:g} s; output {model.output_name} "
            f"[{pretty_unit(model.output_unit)}]; effects: {effects}")


def improvement_sentence(before: dict, after: dict, unit: str) -> str:
    """'RMS error fell from X to Y <unit>; cycle fuel error from A % to B %' from two evaluate() dicts: the
    simulation RMS error [unit] and the signed cumulative fuel error [%] (eq. 20) of the drive cycle, or with
    several cycles their mean followed by their RMS."""
    x, y = before["rmse"]["simulation"], after["rmse"]["simulation"]
    cb, ca = before["cycle_fuel_error_percent"], after["cycle_fuel_error_percent"]
    verb = "fell" if y < x else "rose" if y > x else "stayed"
    n = max(sum(1 for k in c if k not in ("mean", "rms")) for c in (cb, ca))
    if not all(map(math.isfinite, (cb["mean"], ca["mean"]))):
        cycle = "no complete drive cycle for the cycle fuel error"
    elif n > 1:
        cycle = (f"cycle fuel error from {cb['mean']:+.2f} % to {ca['mean']:+.2f} % on average over {n} cycles "
                 f"(RMS {cb['rms']:.2f} % to {ca['rms']:.2f} %)")
    else:
        cycle = f"cycle fuel error from {cb['mean']:+.2f} % to {ca['mean']:+.2f} %"
    return f"RMS error {verb} from {x:.2f} to {y:.2f} {unit}; {cycle}"


# ---- figures (plotly figure dicts) -----------------------------------------------------------------------

def _axis(title: str, **kw) -> dict:
    return {"title": {"text": title}, "zeroline": False, "showline": True, "mirror": True, "ticks": "outside", **kw}


def _layout(title: str, x: str, y: str, height: int = 420, **kw) -> dict:
    return {"title": {"text": title, "x": 0.01}, "xaxis": _axis(x), "yaxis": _axis(y), "height": height,
            "template": "plotly_white", "margin": {"l": 70, "r": 20, "t": 60, "b": 110},
            "legend": {"orientation": "h", "yref": "container", "y": 0, "yanchor": "bottom"}, **kw}


def _minutes(ds, t) -> np.ndarray:
    return (np.asarray(t, float) - ds.t[0]) / 60.0


def time_figure(ds, curves: list[Curve], max_points: int = MAX_POINTS) -> dict:
    """Measured fuel and each model's simulation (and the first model's 1-step prediction) over time."""
    unit = pretty_unit(ds.output_unit)
    tmin = _minutes(ds, ds.t)
    traces = []

    def line(y, name, colour, width=1.2, dash=None, visible=True):
        x, yd = minmax_decimate(tmin, y, max_points)
        traces.append({"type": "scatter", "mode": "lines", "x": x, "y": yd, "name": name, "visible": visible,
                       "line": {"color": colour, "width": width, **({"dash": dash} if dash else {})}})

    line(np.where(ds.valid, ds.y, np.nan), "measured", MEASURED, 1.4)
    for i, c in enumerate(curves):
        line(c.run.on_tested(c.run.ysim), f"{c.label}: simulation", c.colour)
        if i == 0:
            line(c.run.on_tested(c.run.ypred), f"{c.label}: 1-step prediction", "#ff7f0e", 1.0, "dot", "legendonly")
    return {"data": traces, "layout": _layout("Measured fuel flow and the model", "time since start [min]",
                                              f"fuel flow [{unit}]", 460)}


def residual_figure(ds, curves: list[Curve], worst: list[dict], max_points: int = MAX_POINTS) -> dict:
    """Simulation error ŷ_sim − y of each model over time, the worst stretches shaded and labelled."""
    unit = pretty_unit(ds.output_unit)
    tmin = _minutes(ds, ds.t)
    traces = []
    for c in curves:
        x, y = minmax_decimate(tmin, c.run.on_tested(c.run.ysim) - c.run.y, max_points)
        traces.append({"type": "scatter", "mode": "lines", "x": x, "y": y, "name": f"{c.label}: model − measured",
                       "line": {"color": c.colour, "width": 1.0}})
    # one label row per stretch in a band above the curves, so labels of nearby stretches never overlap
    row = 0.065
    shapes, notes = [], []
    for rank, s in enumerate(worst, 1):
        a, b = _minutes(ds, [s["t_start_s"], s["t_end_s"]])
        shapes.append({"type": "rect", "xref": "x", "yref": "paper", "x0": a, "x1": b, "y0": 0, "y1": 1,
                       "fillcolor": "rgba(214,39,40,0.15)", "line": {"width": 0}, "layer": "below"})
        notes.append({"x": (a + b) / 2, "y": 1.0 - row * (rank - 1), "xref": "x", "yref": "paper",
                      "xanchor": "auto", "yanchor": "top", "showarrow": False, "font": {"size": 11, "color": "#a00"},
                      "text": f"#{rank} {', '.join(s['context'])}",
                      "hovertext": f"RMS {s['rmse']:.2f} {unit}, bias {s['bias']:+.2f} {unit}, "
                                   f"{s['speed_rpm']:.0f} rpm"})
    layout = _layout("Simulation error, worst stretches marked", "time since start [min]",
                     f"model − measured [{unit}]", 420 + 30 * len(worst), shapes=shapes, annotations=notes)
    layout["yaxis"]["domain"] = [0.0, 1.0 - row * len(worst)]
    return {"data": traces, "layout": layout}


def effect_signal_figure(ds, curve: Curve, candidate: dict, max_points: int = MAX_POINTS) -> dict | None:
    """A confirmed effect's bus signals over time (right axis, in their DBC units) under the model's simulation
    error (left axis [output unit]), so the engineer sees the fuel step with the signal; None when none of its
    signals is in the data."""
    unit = pretty_unit(ds.output_unit)
    tmin = _minutes(ds, ds.t)
    x, y = minmax_decimate(tmin, curve.run.on_tested(curve.run.ysim) - curve.run.y, max_points)
    traces = [{"type": "scatter", "mode": "lines", "x": x, "y": y, "name": f"{curve.label}: model − measured",
               "line": {"color": curve.colour, "width": 1.0}}]
    units = signal_units()
    shown = [s for s in candidate.get("signals", []) if s in ds.extra]
    for k, name in enumerate(shown):
        x, y = minmax_decimate(tmin, ds.extra[name], max_points)
        traces.append({"type": "scatter", "mode": "lines", "x": x, "y": y, "yaxis": "y2",
                       "name": f"{name} [{units.get(name, '-')}]",
                       "line": {"color": COLOURS[(k + 2) % len(COLOURS)], "width": 1.4, "shape": "hv"}})
    if not shown:
        return None
    axis2 = ", ".join(f"{n} [{units.get(n, '-')}]" for n in shown)
    layout = _layout(f"{candidate.get('name', candidate['effect'])}: its signal and the model's error",
                     "time since start [min]", f"model − measured [{unit}]", 420)
    layout["yaxis2"] = _axis(axis2, overlaying="y", side="right", showgrid=False, mirror=False)
    return {"data": traces, "layout": layout}


def correlation_figure(title: str, tests: list[tuple[str, str, dict]], Ts: float, min_lag: int | None = None) -> dict:
    """Bars of normalised correlations r(h) [-] over lag h·Ts [s], h ≥ min_lag, with the ±99 % bound of each
    test; tests: (name, colour, {"lags", "r", "bound", "passed"}) as in diagnosis['where_it_fails']['whiteness']."""
    traces = []
    for label, colour, t in tests:
        name = f"{label}: {'pass' if t['passed'] else 'FAIL'}"
        lags = np.asarray(t["lags"])
        keep = lags >= (lags.min() if min_lag is None else min_lag)
        lag_s = lags[keep] * Ts
        traces.append({"type": "bar", "x": lag_s, "y": np.asarray(t["r"], float)[keep], "name": name,
                       "legendgroup": name, "marker": {"color": colour}})
        for sign in (1, -1):
            traces.append({"type": "scatter", "mode": "lines", "x": [lag_s[0], lag_s[-1]],
                           "y": [sign * t["bound"]] * 2, "showlegend": sign == 1, "hoverinfo": "skip",
                           "legendgroup": name, "name": f"99 % bound ±{t['bound']:.3f}",
                           "line": {"color": colour, "dash": "dash", "width": 1.2}})
    return {"data": traces, "layout": _layout(title, "lag [s]", "normalised correlation [-]", 340,
                                              barmode="group", bargap=0.3)}


def error_map_figure(emap: dict, output_unit: str, which: str = "mean_error") -> dict:
    """Heat map of diagnosis['where_it_fails']['error_map'][which] (mean or RMS simulation error per speed ×
    torque cell [output unit]); empty cells (too few samples) are blank."""
    unit, t_unit = pretty_unit(output_unit), pretty_unit(emap["torque_unit"])
    z = np.array(emap[which], dtype=float).T  # rows: torque bins, columns: speed bins
    rms, cnt = np.array(emap["rms_error"], float).T, np.array(emap["count"]).T
    mean = np.array(emap["mean_error"], float).T
    bias = which == "mean_error"
    trace = {"type": "heatmap", "x": emap["speed_edges_rpm"], "y": emap["torque_edges"], "z": z,
             "customdata": np.dstack([mean, rms, cnt]),
             "colorscale": "RdBu" if bias else "Viridis", "reversescale": bias,
             "colorbar": {"title": {"text": f"{'mean' if bias else 'RMS'} error [{unit}]", "side": "right"}},
             "hovertemplate": f"%{{x:.0f}} rpm, %{{y:.0f}} {t_unit}<br>mean error %{{customdata[0]:+.2f}} {unit}"
                              f"<br>RMS error %{{customdata[1]:.2f}} {unit}<br>%{{customdata[2]}} samples"
                              "<extra></extra>"}
    if bias:
        trace["zmid"] = 0.0
    title = "Bias (model − measured)" if bias else "RMS error"
    return {"data": [trace], "layout": _layout(f"{title} over speed × torque", "engine speed [rpm]",
                                               f"engine torque [{t_unit}]", 420)}


MAP_GRID = 40  # points per axis of the engine-map figures


def engine_map_figures(model, true_map=None) -> list[tuple[str, dict]]:
    """The engine model's steady-state map f(n, T) [output unit] (ident.hammerstein.steady_state_map) as a heat map
    with contours over its region (speed [rpm] × torque [the model's unit]), cells without identification data
    (ident.enginemap.EngineMap.covered) left blank; beside it `true_map(n, T)` [output unit] on the same grid (the
    simulator's engine, when the data come from it; blank where the identified map has no data too, so the two
    compare where they can). [] for a model without an engine map."""
    emap = engine_map_of(model)
    if emap is None:
        return []
    n = np.linspace(*emap.speed_range, MAP_GRID)
    T = np.linspace(*emap.torque_range, MAP_GRID)
    gn, gt = np.meshgrid(n, T)  # rows: torque, columns: speed
    covered = emap.covered(gn, gt)
    unit, t_unit = pretty_unit(model.output_unit), pretty_unit(emap.torque_unit)
    maps = [("engine_map", "Identified engine map (steady state)", steady_state_map(model, gn, gt))]
    if true_map is not None:
        maps.append(("true_map", "True engine map (simulator)", np.asarray(true_map(gn, gt), float)))
    top = max(float(np.nanmax(np.where(covered, z, np.nan))) for _, _, z in maps)
    figs = []
    for name, title, z in maps:
        trace = {"type": "contour", "x": n, "y": T, "z": np.where(covered, z, np.nan), "zmin": 0.0, "zmax": top,
                 "colorscale": "Viridis", "contours": {"coloring": "heatmap", "showlabels": True},
                 "colorbar": {"title": {"text": f"fuel [{unit}]", "side": "right"}},
                 "hovertemplate": f"%{{x:.0f}} rpm, %{{y:.0f}} {t_unit}<br>%{{z:.2f}} {unit}<extra></extra>"}
        figs.append((name, {"data": [trace], "layout": _layout(f"{title}; blank: no identification data",
                                                                "engine speed [rpm]", f"engine torque [{t_unit}]",
                                                                420)}))
    return figs


def _plot(fig: dict, div_id: str) -> str:
    # plotly takes about a second to import: loaded only when a report is drawn
    import plotly.graph_objects as go  # validates every property name and value
    import plotly.io as pio

    return pio.to_html(go.Figure(fig), include_plotlyjs=False, full_html=False, config=PLOTLY_CONFIG,
                       div_id=div_id, default_width="100%", default_height=f"{fig['layout']['height']}px")


# ---- tables and text -------------------------------------------------------------------------------------

def _table(head: list[str] | None, rows: list[list[str]], cls: str = "") -> str:
    """An HTML table (no header row when head is None); head and cells are HTML already."""
    th = "" if head is None else "<thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead>"
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}">{th}<tbody>{body}</tbody></table>'


def _signals(c: dict) -> str:
    spns = ", ".join(map(str, c.get("spns") or []))
    return ", ".join(map(_name, c.get("signals") or [])) + (f"<br><small>SPN {_esc(spns)}</small>" if spns else "")


def _effect(c: dict) -> str:
    """The effect id, and its name unless that only repeats a signal name (generic bus-signal candidates)."""
    name = c.get("name", "")
    own = name and not any(sig in name for sig in c.get("signals") or [])
    return f"<b>{_name(c['effect'])}</b>" + (f"<br><small>{_esc(name)}</small>" if own else "")


def effects_table(candidates: list[dict], top: int = 12) -> str:
    """The ranked candidates (diagnosis['candidates'], best first) with their evidence; the testable ones after
    `top` and the untestable ones folded away."""
    head = ["#", "effect", "bus signals (SPN)", "LM statistic<br>(df)", "p-value", "Holm p", "status",
            "held-out<br>RMS drop [%]", "what it means"]
    rows = []
    testable = [c for c in candidates if c.get("testable", c.get("statistic") is not None)]
    for rank, c in enumerate(testable, 1):
        status = _esc(c.get("status", "named" if c.get("significant") else ""))
        named = f'<span class="yes">{status}</span>' if c.get("recommended") else status
        rows.append([str(rank), _effect(c),
                     _signals(c), f"{_fmt(c.get('statistic'), '.1f')} ({c.get('df', '–')})",
                     _fmt(c.get("p_value"), '.2e'), _fmt(c.get("p_holm"), '.2e'),
                     named, _fmt(c.get("rmse_drop_percent"), '.1f'),
                     _esc(c.get("explanation", ""))])
    out = _table(head, rows[:top], "effects")
    if rows[top:]:
        out += (f"<details><summary>{len(rows) - top} more tested candidate{'s' * (len(rows) - top != 1)}</summary>"
                f"{_table(head, rows[top:], 'effects')}</details>")
    untestable = [c for c in candidates if c not in testable]
    if untestable:
        items = "".join(f"<li>{_effect(c)} ({_signals(c)}): {_esc(c.get('explanation', ''))}</li>"
                        for c in untestable)
        out += (f"<details><summary>{len(untestable)} candidate{'s' * (len(untestable) != 1)} not testable on "
                f"this data</summary>"
                f"<ul>{items}</ul></details>")
    return out


def engine_map_paragraph(diagnosis: dict) -> str:
    """What the diagnosis says of the engine's own map (a property of the engine, not a missing effect); empty for a
    saved result without it."""
    m = diagnosis.get("engine_map")
    if not isinstance(m, dict):
        return ""
    return f'<p class="note"><b>Engine map</b> ({_esc(m["status"])}): {_esc(m.get("explanation", ""))}.</p>'


def worst_table(worst: list[dict], ds) -> str:
    """The worst stretches with their context (diagnosis['where_it_fails']['worst_segments'])."""
    unit, t_unit = pretty_unit(ds.output_unit), pretty_unit(ds.input_units[1])
    rows = [[f"#{i}", f"{_minutes(ds, s['t_start_s']):.2f}–{_minutes(ds, s['t_end_s']):.2f}",
             f"{s['rmse']:.2f}", f"{s['bias']:+.2f}", f"{s['speed_rpm']:.0f}", f"{s['torque']:.0f}",
             _esc(", ".join(s["context"]))] for i, s in enumerate(worst, 1)]
    return _table(["#", "time since start [min]", f"RMS error [{unit}]", f"bias [{unit}]", "speed [rpm]",
                   f"torque [{t_unit}]", "what differs there from the rest of the trip"], rows)


def metrics_table(curves: list[Curve], unit: str) -> str:
    """The validation metrics of each model side by side (columns: models)."""
    unit = pretty_unit(unit)

    def passes(w):
        failed = [k for k, v in w["crosscorr_pass"].items() if not v]
        cross = f"FAIL: {_esc(', '.join(failed))}" if failed else f"pass ({len(w['crosscorr_pass'])} inputs)"
        return ("pass" if w["autocorr_pass"] else "FAIL"), cross

    rows = [["fit, simulation [%]"], ["fit, 1-step prediction [%]"], [f"RMS error, simulation [{unit}]"],
            [f"RMS error, 1-step prediction [{unit}]"], ["cycle fuel error, mean [%]"],
            ["cycle fuel error, RMS [%]"], ["residual whiteness (99 %)"], ["input cross-correlation (99 %)"]]
    for c in curves:
        m = c.metrics
        cyc = m["cycle_fuel_error_percent"]
        white, cross = passes(m["whiteness"])
        for row, v in zip(rows, [_fmt(m["fit_percent"]["simulation"], ".1f"),
                                 _fmt(m["fit_percent"]["prediction"], ".1f"), _fmt(m["rmse"]["simulation"], ".3f"),
                                 _fmt(m["rmse"]["prediction"], ".3f"), _fmt(cyc["mean"], "+.2f"),
                                 _fmt(cyc["rms"], ".2f"), white, cross]):
            row.append(v)
    head = ["", *(f'<span style="color:{c.colour}">■</span> {_esc(c.label)}' for c in curves)]
    return _table(head, rows, "metrics")


def clock(t: float) -> str:
    """A grid time [s]: UTC date-time when it is Unix time (after 2001), else seconds."""
    return f"{dt.datetime.fromtimestamp(t, dt.timezone.utc):%Y-%m-%d %H:%M:%S} UTC" if t > 1e9 else f"{t:.1f} s"


def time_range_text(ds) -> str:
    """First to last sample, the span and the valid duration."""
    a, b = float(ds.t[0]), float(ds.t[-1])
    n = len(ds.segments())
    return (f"{clock(a)} – {clock(b)} ({(b - a) / 60:.1f} min; {ds.valid.sum() * ds.Ts / 60:.1f} min valid in "
            f"{n} segment{'s' * (n != 1)})")


CSS = """
body{font-family:"DejaVu Sans",Arial,sans-serif;margin:0 auto;max-width:1400px;padding:0 20px 40px;color:#222}
h1{font-size:1.6em;margin:.6em 0 .2em} h2{font-size:1.25em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em} td,th{border:1px solid #ccc;padding:3px 7px;
vertical-align:top;text-align:left;overflow-wrap:break-word} th{background:#f2f2f2;white-space:nowrap}
table.effects{width:100%} table.effects td:nth-child(2),table.effects td:nth-child(3){max-width:14em}
table.effects td:nth-child(n+4):nth-child(-n+8),
table.metrics td{text-align:right;white-space:nowrap} table.metrics td:first-child{text-align:left}
.header td:first-child{font-weight:bold;white-space:nowrap} .verdict{font-size:1.1em;padding:.6em .9em;
background:#fff6e0;border-left:4px solid #f0a000} .improvement{font-size:1.15em;padding:.6em .9em;
background:#e8f6e8;border-left:4px solid #2ca02c} .yes{color:#b00;font-weight:bold} .note{color:#555;
font-size:.9em} .grid{display:grid;grid-template-columns:1fr 1fr;gap:10px} .grid>div{min-width:0}
"""


def render_report(model, ds, diagnosis: dict | None = None, after=(), *, label: str | None = None,
                  title: str | None = None, truck: str | None = None, files=(), max_points: int = MAX_POINTS,
                  top: int = 12, true_map=None) -> str:
    """The report of `model` (ident.polymodel.PolyModel) on dataset ds as one HTML page (module docstring).

    diagnosis: ident.diagnosis.diagnose(model, ds) when already computed (else it is computed here; its model run
    is reused), or a saved `fuelid diagnose --json` result (the model is run again); after:
    (label, PolyModel) pairs of models refitted with effects added, compared on the same data; label: the
    model's own (e.g. its file name; default "before" beside AFTER models, else "model"); truck, files:
    for the header; max_points: the decimation budget per time-series trace; top: candidates shown unfolded;
    true_map: the engine's true steady-state map (n [rpm], T [torque unit]) → fuel [output unit], drawn beside an
    engine model's identified one (`engine_map_figures`).
    Raises ValueError (from the diagnosis) when no valid segment is long enough; FuelidError on unit mismatch.
    """
    import plotly.offline  # heavy: loaded only when a report is drawn (see _plot)

    diagnosis = diagnosis if diagnosis is not None else diagnose(model, ds)
    if isinstance(diagnosis, Diagnosis):  # its model run is the report's
        run, diagnosis = diagnosis.run, diagnosis.to_json()
    else:  # a saved `fuelid diagnose --json`: the model is run again
        run = tested_run(model, ds)
    unit = ds.output_unit
    curves = [Curve(label or ("before" if after else "model"), COLOURS[0], model, run, diagnosis["compare"])]
    for i, (label, m) in enumerate(after, 1):
        run = tested_run(m, ds)
        curves.append(Curve(label, COLOURS[i % len(COLOURS)], m, run, metrics(run, ds)))
    fails = diagnosis["where_it_fails"]
    white = fails["whiteness"]
    worst = fails["worst_segments"]
    max_lag = len(white["autocorr"]["lags"]) - 1
    title = title or f"fuelid diagnosis report{f' — {truck}' if truck else ''}"

    def corr(c: Curve):  # the whiteness tests of an AFTER model, as the diagnosis reports the model's
        eps = c.run.eps
        auto = autocorr_test(eps, max_lag)
        cross = crosscorr_test(eps, np.where(np.isfinite(eps)[:, None], c.run.u[:, :2], np.nan), max_lag)
        as_dict = lambda t: {"lags": t.lags, "r": t.r, "bound": t.bound, "passed": t.passed}  # noqa: E731
        return as_dict(auto), [as_dict(t) for t in cross]

    extra = [corr(c) for c in curves[1:]]
    figs = [("time", time_figure(ds, curves, max_points)), ("residual", residual_figure(ds, curves, worst, max_points)),
            ("autocorr", correlation_figure(
                "Residual auto-correlation r_e(h), h ≥ 1",
                [(curves[0].label, curves[0].colour, white["autocorr"])]
                + [(c.label, c.colour, e[0]) for c, e in zip(curves[1:], extra)], ds.Ts, min_lag=1))]
    for j, name in enumerate(model.input_names[:2]):
        test = white["crosscorr"][name]
        figs.append((f"crosscorr{j}", correlation_figure(
            f"Residual × {name}, r_eu(h)",
            [(curves[0].label, curves[0].colour, test)]
            + [(c.label, c.colour, e[1][j]) for c, e in zip(curves[1:], extra)], ds.Ts)))
    figs += [("map_bias", error_map_figure(fails["error_map"], unit, "mean_error")),
             ("map_rms", error_map_figure(fails["error_map"], unit, "rms_error"))]
    confirmed = [c for c in diagnosis["candidates"] if c.get("recommended")]
    effect_figs = [(f"effect{k}", fig) for k, c in enumerate(confirmed)
                   if (fig := effect_signal_figure(ds, curves[0], c, max_points)) is not None]
    figs += effect_figs
    map_figs = engine_map_figures(model, true_map)
    figs += map_figs
    plots = {name: _plot(fig, f"fig-{name}") for name, fig in figs}
    map_section = "" if not map_figs else f"""<h3>The engine map (part of the model)</h3>
<p class="note">The model's steady state f(n, T) = y0 + G_n(1)(n − n0) + G_T(1)(T − T0) + m(n, T): the plane its
speed and torque paths carry and the engine map beyond it (docs/explanation/engine-model.md), over the region of
the identification data.</p>
<div class="grid">{"".join(plots[name] for name, _ in map_figs)}</div>"""

    header_rows = [["truck", _esc(truck or "unknown")],
                   ["data", _esc(", ".join(map(str, files)) or "(dataset given directly)")],
                   ["time range", _esc(time_range_text(ds))],
                   [_esc(curves[0].label), _esc(structure_text(model))],
                   *[[_esc(c.label), _esc(structure_text(c.model))] for c in curves[1:]],
                   ["generated", f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M:%S} UTC by fuelid "
                                 f"{_esc(__version__)}"]]
    test = diagnosis.get("test", {})
    n_cycles = sum(k.isdigit() for k in diagnosis["compare"]["cycle_fuel_error_percent"])
    sentences = "".join(f'<p class="improvement">{_esc(c.label)}: '
                        f'{_esc(improvement_sentence(curves[0].metrics, c.metrics, pretty_unit(unit)))}.</p>'
                        for c in curves[1:])
    decimated = (f"Curves with more than {max_points} points are min/max decimated (each bucket of consecutive "
                 f"samples keeps its lowest and highest value), so peaks survive any zoom but detail finer than a "
                 f"bucket does not. Time axis: minutes since {_esc(clock(float(ds.t[0])))}.")
    body = f"""
<h1>{_esc(title)}</h1>
{_table(None, header_rows, "header")}
<p class="verdict">{_esc(diagnosis.get("verdict", ""))}</p>
<h2>Compare: model{'s before and after' if after else ''} vs measurements</h2>
{sentences}
{metrics_table(curves, unit)}
<p class="note">RMS error of the simulation; cycle fuel error: cumulative fuel of the model vs measured per drive
cycle (paper eq. 20), mean and RMS over the {n_cycles} drive cycle{'s' * (n_cycles != 1)}.</p>
{plots["time"]}
<p class="note">{decimated} Drag to zoom, double-click to reset; the 1-step prediction is in the legend.</p>
<h2>Where it fails</h2>
{plots["residual"]}
{worst_table(worst, ds)}
<h3>Whiteness (99 % bounds, paper eqs. 18–19, Fig. 7)</h3>
<p class="note">Normalised correlations of the 1-step prediction errors; a model passes when every bar stays inside
its dashed bounds, at lags h ≥ 1 for r_e and h ≥ 0 for r_eu (negative lags, fuel leading the input, show feedback
and are not tested).</p>
<p class="note">{_esc(WHITENESS_MEANING)}</p>
<div class="grid">{plots["autocorr"]}{"".join(plots[f"crosscorr{j}"] for j in range(len(model.input_names[:2])))}</div>
<h3>Error over engine speed × torque</h3>
<div class="grid">{plots["map_bias"]}{plots["map_rms"]}</div>
{map_section}
<h2>Which effect is missing</h2>
<p class="note">{_esc(test.get("method", ""))}; family-wise α = {_esc(test.get("alpha", ""))},
{_esc(test.get("candidates_tested", ""))} candidates tested on {_esc(test.get("samples", ""))} samples.</p>
{engine_map_paragraph(diagnosis)}
{effects_table(diagnosis["candidates"], top)}
{"".join(plots[name] for name, _ in effect_figs)}
"""
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_esc(title)}</title>'
            f'<style>{CSS}</style><script type="text/javascript">{plotly.offline.get_plotlyjs()}</script></head>'
            f"<body>{body}</body></html>\n")


def write_report(path, model, ds, **kwargs) -> Path:
    """render_report(model, ds, **kwargs) written to `path` (UTF-8); returns the path."""
    path = Path(path)
    path.write_text(render_report(model, ds, **kwargs), encoding="utf-8")
    return path
