"""ident.report: the diagnosis report's pieces on synthetic data with a hidden DPF regeneration — the numbers on the
page are the diagnosis's, every axis has its unit, and the page fetches nothing."""
import dataclasses
import re
import warnings
from html.parser import HTMLParser

import numpy as np
import pytest

from fuelid.ident import diagnosis as dg
from fuelid.ident import report as rp
from fuelid.ident.diagnosis import failures
from fuelid.ident.diagnosis.run import run_gradients
from fuelid.ident.modeldata import apply_effects
from fuelid.ident.modelrun import run_model
from fuelid.ident.pem import pem
from fuelid.ident.validation import evaluate
from tests.ident import hidden


def fit(ds, effects=()):
    """The hidden-data structure fitted by PEM, with the effects' extra inputs (as `fuelid identify --effect`)."""
    fx = apply_effects(ds, list(effects))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(np.hstack([ds.u, fx.u]), fx.y, fx.extend(hidden.STRUCTURE), ds.Ts,
                u0=np.r_[ds.u0, np.zeros(fx.u.shape[1])], y0=ds.y0)
    return dataclasses.replace(m, input_names=ds.input_names + fx.names, input_units=ds.input_units + fx.units,
                               output_name=ds.output_name, output_unit=ds.output_unit, effects=fx.effects)


@pytest.fixture(scope="module")
def case():
    """(dataset, model, diagnosis, after model, page) for a 15-minute trip with two DPF regenerations."""
    ds = hidden.make("dpf_regeneration", n=3000, seed=2)
    model, after = fit(ds), fit(ds, ["dpf_regeneration"])
    found = dg.diagnose(model, ds)
    diagnosis = found.to_json()
    page = rp.render_report(model, ds, found, after=[("with DPF", after)], truck="TRUCK-42",
                            files=["trip.mcap"], top=5)
    return ds, model, diagnosis, after, page


class Tables(HTMLParser):
    """Every <table> on a page as rows of cell texts; and every src/href attribute."""

    def __init__(self, page):
        super().__init__()
        self.tables, self.links, self._cell = [], [], None
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        self.links += [v for k, v in attrs if k in ("src", "href") and v]
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append(self._cell.strip())
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def test_minmax_decimation_keeps_extremes_gaps_and_budget():
    x = np.arange(100_000) * 0.3
    y = np.sin(x / 50)
    y[12_345], y[67_890] = 9.0, -7.0  # single-sample spikes
    y[40_000:40_010] = np.nan  # a gap
    xd, yd = rp.minmax_decimate(x, y, 2000)
    assert len(xd) <= 2000 + 2
    assert np.nanmax(yd) == 9.0 and np.nanmin(yd) == -7.0
    assert np.all(np.diff(xd[np.isfinite(yd)]) > 0)  # time order kept
    gap = np.flatnonzero(np.isnan(yd))
    assert len(gap) == 1 and xd[gap[0] - 1] < 40_000 * 0.3 and xd[gap[0] + 1] >= 40_010 * 0.3
    short = np.arange(50.0)
    assert len(rp.minmax_decimate(short, short, 2000)[0]) == 50  # within budget: kept whole


def test_improvement_sentence():
    """The cycle fuel error keeps its sign; with several cycles the sentence gives their mean and their RMS."""
    before = {"rmse": {"simulation": 2.2307}, "cycle_fuel_error_percent": {"0": -2.67, "mean": -2.67, "rms": 2.67}}
    after = {"rmse": {"simulation": 1.0249}, "cycle_fuel_error_percent": {"0": 0.05, "mean": 0.05, "rms": 0.05}}
    assert rp.improvement_sentence(before, after, "L/h") == \
        "RMS error fell from 2.23 to 1.02 L/h; cycle fuel error from -2.67 % to +0.05 %"
    assert rp.improvement_sentence(after, before, "kg/h").startswith("RMS error rose from 1.02 to 2.23 kg/h")
    two = {"rmse": {"simulation": 1.0}, "cycle_fuel_error_percent": {"0": 1.0, "1": -3.0, "mean": -1.0, "rms": 2.236}}
    assert rp.improvement_sentence(before, two, "L/h").endswith(
        "cycle fuel error from -2.67 % to -1.00 % on average over 2 cycles (RMS 2.67 % to 2.24 %)")


def test_effects_table_numbers_are_the_diagnosis(case):
    ds, model, diagnosis, after, page = case
    table = next(t for t in Tables(page).tables if t[0][:3] == ["#", "effect", "bus signals (SPN)"])
    testable = [c for c in diagnosis["candidates"] if c["testable"]]
    assert len(table) - 1 == 5  # top=5 unfolded; the rest folded away below
    for row, c in zip(table[1:], testable):
        assert row[1].startswith(c["effect"])
        assert row[3] == f"{c['statistic']:.1f} ({c['df']})"
        assert row[4] == f"{c['p_value']:.2e}" and row[5] == f"{c['p_holm']:.2e}"
        assert row[6] == c["status"]
        assert row[7] == ("–" if c["rmse_drop_percent"] is None else f"{c['rmse_drop_percent']:.1f}")
        assert row[8] == c["explanation"]
        assert all(str(spn) in row[2] for spn in c["spns"])
    top = table[1]
    assert top[1].startswith("dpf_regeneration") and "3700" in top[2] and top[6] == "recommended"  # the hidden one
    assert diagnosis["verdict"] in page


def test_compare_worst_and_sentence_match_the_metrics(case):
    ds, model, diagnosis, after, page = case
    tables = Tables(page).tables
    metrics = next(t for t in tables if t[0][1:] == ["■ before", "■ with DPF"])
    rows = {r[0]: r[1:] for r in metrics}
    a = evaluate(after, ds)
    c = diagnosis["compare"]
    assert rows["fit, simulation [%]"] == [f"{m['fit_percent']['simulation']:.1f}" for m in (c, a)]
    assert rows["RMS error, simulation [L/h]"] == [f"{c['rmse']['simulation']:.3f}", f"{a['rmse']['simulation']:.3f}"]
    cyc = [m["cycle_fuel_error_percent"]["mean"] for m in (c, a)]  # one drive cycle: its signed error
    sentence = f"RMS error fell from {c['rmse']['simulation']:.2f} to {a['rmse']['simulation']:.2f} L/h; cycle fuel " \
               f"error from {cyc[0]:+.2f} % to {cyc[1]:+.2f} %"
    assert sentence in page and a["rmse"]["simulation"] < 0.8 * c["rmse"]["simulation"]

    worst = next(t for t in tables if t[0][:2] == ["#", "time since start [min]"])
    for row, s in zip(worst[1:], diagnosis["where_it_fails"]["worst_segments"]):
        assert row[1] == f"{(s['t_start_s'] - ds.t[0]) / 60:.2f}–{(s['t_end_s'] - ds.t[0]) / 60:.2f}"
        assert row[1] == f"{s['t_start_min']:.2f}–{s['t_end_min']:.2f}"  # the CLI prints these
        assert row[2] == f"{s['rmse']:.2f}" and row[6] == ", ".join(s["context"])
    assert "DPF active regeneration" in worst[1][6]


def test_the_model_is_labelled_as_the_caller_names_it(case):
    ds, model, diagnosis, after, _ = case
    page = rp.render_report(model, ds, diagnosis, after=[("after.json", after)], label="before.json")
    metrics = next(t for t in Tables(page).tables if t[0][1:] == ["■ before.json", "■ after.json"])
    assert len(metrics) > 1


def test_worst_stretches_are_labelled_only_with_what_differs_from_the_trip(case, monkeypatch):
    """The hidden DPF regeneration runs in part of the trip: it labels the worst stretches. A condition on for the
    whole trip labels none."""
    ds, model, diagnosis, after, _ = case
    worst = diagnosis["where_it_fails"]["worst_segments"]
    assert "DPF active regeneration" in worst[0]["context"]
    flags = {**failures.context_flags(ds), "always on": np.ones(len(ds), bool)}
    monkeypatch.setattr(failures, "context_flags", lambda ds: flags)
    again = failures.worst_segments(ds, run_gradients(run_model(model, ds)))
    assert [s["t_start_s"] for s in again] == [s["t_start_s"] for s in worst]
    assert all("always on" not in s["context"] and "DPF active regeneration" in s["context"] for s in again[:1])


def test_a_confirmed_effects_signal_is_plotted_beside_the_error(case):
    """The DPF regeneration status, as logged, on the right axis in its unit, over the model's error: the page
    holds that figure, and only confirmed effects get one."""
    ds, model, diagnosis, after, page = case
    dpf = next(c for c in diagnosis["candidates"] if c["effect"] == "dpf_regeneration")
    assert dpf["significant"]
    fig = rp.effect_signal_figure(ds, rp.Curve("model", "#000", model, run_model(model, ds), diagnosis["compare"]), dpf)
    signal = next(t for t in fig["data"] if t.get("yaxis") == "y2")
    assert signal["name"].startswith("DPFC1.DPFActiveRegenStatus [") and max(signal["y"]) == 1
    assert fig["layout"]["yaxis"]["title"]["text"] == "model − measured [L/h]"
    assert fig["layout"]["yaxis2"]["title"]["text"].startswith("DPFC1.DPFActiveRegenStatus")
    assert 'id="fig-effect0"' in page and 'id="fig-effect1"' not in page
    level = {"effect": "level:X", "signals": ["NOT.InTheData"], "significant": True}
    assert rp.effect_signal_figure(ds, rp.Curve("model", "#000", model, run_model(model, ds), {}), level) is None


def test_figures_carry_the_diagnosis_numbers_and_units(case):
    ds, model, diagnosis, after, page = case
    fails = diagnosis["where_it_fails"]
    emap = rp.error_map_figure(fails["error_map"], "L/h")
    z = np.array(emap["data"][0]["z"], float)
    expected = np.array([[np.nan if v is None else v for v in row] for row in fails["error_map"]["mean_error"]]).T
    np.testing.assert_array_equal(z, expected)
    assert emap["layout"]["xaxis"]["title"]["text"] == "engine speed [rpm]"
    assert emap["layout"]["yaxis"]["title"]["text"] == "engine torque [N·m]"
    assert emap["data"][0]["colorbar"]["title"]["text"] == "mean error [L/h]"

    auto = fails["whiteness"]["autocorr"]
    fig = rp.correlation_figure("r_e", [("before", "#000", auto)], ds.Ts, min_lag=1)
    np.testing.assert_allclose(fig["data"][0]["y"], auto["r"][1:])
    np.testing.assert_allclose(fig["data"][0]["x"], np.arange(1, len(auto["lags"])) * ds.Ts)
    assert fig["data"][1]["y"] == [auto["bound"]] * 2 and fig["data"][2]["y"] == [-auto["bound"]] * 2

    run = run_model(model, ds)
    curves = [rp.Curve("before", "#000", model, run, diagnosis["compare"])]
    res = rp.residual_figure(ds, curves, fails["worst_segments"])
    assert [n["text"].split(" ", 1)[1] for n in res["layout"]["annotations"]] == \
        [", ".join(s["context"]) for s in fails["worst_segments"]]
    for fig in (rp.time_figure(ds, curves), res, fig, emap):
        for axis in ("xaxis", "yaxis"):
            assert re.search(r"\[[^\]]+\]$", fig["layout"][axis]["title"]["text"]), fig["layout"][axis]
    for axis_title in ("fuel flow [L/h]", "time since start [min]", "lag [s]", "normalised correlation [-]",
                       "engine speed [rpm]", "RMS error [L/h]"):
        assert '"%s"' % axis_title.replace("/", r"\u002f") in page  # in the embedded figures' JSON


def test_header_and_self_contained(case):
    ds, model, diagnosis, after, page = case
    header = {r[0]: r[1] for r in Tables(page).tables[0]}
    assert header["truck"] == "TRUCK-42" and header["data"] == "trip.mcap"
    assert "nb=1 nf=1 nk=2" in header["before"] and "nc=1 nd=1" in header["before"]
    assert "effects: dpf_regeneration" in header["with DPF"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC by fuelid \S+", header["generated"])
    assert header["time range"].startswith("0.0 s – 899.7 s (15.0 min")
    links = Tables(page).links
    assert not [u for u in links if re.match(r"\s*(https?:)?//", u, re.I)], links
    assert "<script src" not in page and "<link" not in page
    assert "plotly.js v" in page  # the library itself is inlined


def test_an_engine_model_s_map_is_drawn_where_the_data_cover_it_beside_the_true_one():
    from fuelid.ident.identify import identify_model
    from tests.ident import engine_data

    model = identify_model(engine_data.trip(k=1.0, n=4000), hidden.STRUCTURE, ["engine_map"])
    figs = dict(rp.engine_map_figures(model, true_map=engine_data.steady_state))
    assert set(figs) == {"engine_map", "true_map"}
    z, truth = (np.array(figs[k]["data"][0]["z"], float) for k in ("engine_map", "true_map"))
    blank = np.isnan(z)
    assert blank.any() and not blank.all() and np.array_equal(blank, np.isnan(truth))  # compared where covered
    assert np.sqrt(np.nanmean((z - truth) ** 2)) < 0.5  # L/h; the map spans about 50 L/h
    assert rp.engine_map_figures(identify_model(engine_data.trip(k=0.0, n=4000), hidden.STRUCTURE)) == []
    assert "contour" in figs["engine_map"]["data"][0]["type"] and "rpm" in figs["engine_map"]["layout"]["xaxis"]["title"]["text"]
