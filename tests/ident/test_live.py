"""Live adapter: decoded records in, /ident/* records and model.json snapshots out; light import."""
import subprocess
import sys

import numpy as np

from ident.live import LiveEstimator
from tests.conftest import REPO
from tests.ident.online_data import SIGMA_E, diesel_truth
from tests.ident.synthetic import paper_data


def records(u, y, ts=0.3, t0=1000.0, skip=()):
    """EEC1 and LFE1 records (engine, sa 0) three per bin, from deviation data (speed + 600 rpm, torque %)."""
    for k in range(len(y)):
        if k in skip:
            continue
        for j in range(3):
            t = t0 + k * ts + j * ts / 3 + 0.01
            yield "/j1939/EEC1", t, {"sa": 0, "EngSpeed": 600.0 + u[k, 0], "ActualEngPercentTorque": u[k, 1]}
            yield "/j1939/LFE1", t + 0.001, {"sa": 0, "EngFuelRate": y[k] if k % 500 > 20 else None}
        yield "/j1939/LFE1", t0 + k * ts + 0.2, {"sa": 49, "EngFuelRate": None}  # another ECU: ignored


def test_live_estimator_tracks_and_writes(tmp_path):
    from ident.modelfile import load_model

    truth = diesel_truth()
    truth.input_units, truth.output_unit, truth.u0 = ("rpm", "%"), "L/h", (600.0, 0.0)
    u, y, _ = paper_data(truth, n=3000, seed=4, sigma_e=SIGMA_E)
    snap = tmp_path / "model.json"
    live = LiveEstimator.from_model(truth, forgetting=0.9995, snapshot_path=snap, snapshot_every_s=120)
    assert live.torque_unit == "%" and live.fuel == "lfe1"
    out = {}
    gap = set(range(2000, 2200))  # 60 s of silence: the filters restart
    for topic, t, rec in records(u, y, skip=gap):
        for topic_out, t_out, r in live.feed(topic, t, rec):
            out.setdefault(topic_out, []).append(r)
    pred, res = out["/ident/prediction"], out["/ident/residual"]
    assert len(pred) == len(res) == len(y) - len(gap) - 1  # the last bin is still open
    eps = np.array([r["eps"] for r in res if r["eps"] is not None])
    assert np.std(eps[100:]) < 2 * SIGMA_E
    assert any(r["measured"] is None for r in pred)  # LFE1 not available: no update, prediction goes on
    assert all(r["predicted"] is not None for r in pred)
    par = out["/ident/parameters"][-1]
    assert len(par["theta"]) == 41 and par["names"][0].startswith("b1")
    assert abs(par["dc_gain"][1] / 0.477 - 1) < 0.1
    assert load_model(snap).structure == truth.structure


def test_imports_lightly():
    code = "import sys, ident.live; print(any(m.startswith('scipy') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
