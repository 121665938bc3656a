"""The console's API in-process (FastAPI TestClient, stand-in job runner), on SQLite and PostgreSQL: fleet
summary with drift of a known size against each truck's first model and the fleet median, alerts, how the
fleet view keeps up with new and deleted rows, truck history, report links, the page's security headers, and
roles."""
import statistics

import pytest
from fastapi.testclient import TestClient

from fuelid.fleet import auth, console, db
from fuelid.fleet.app import Settings, create_app
from tests.fleet.fake_server import FakeRunner
from tests.fleet.simulated_fleet import engine_model, simulated_fleet, store_version

# The engine's DC gains [L/h per rpm, per N·m] and the default points' mean deviations from idle: steady fuel
# above idle K = G1 · 600 rpm + G2 · 1200 N·m for an efficiency factor of 1 (tests.fleet.simulated_fleet).
G1, G2 = 0.006 / 0.5, 0.018 / 0.7
K = G1 * 600 + G2 * 1200


@pytest.fixture
def fleet(tmp_path, database):
    app = create_app(Settings(data_dir=tmp_path / "data", database_url=database, refit_after_s=None),
                     runner_factory=FakeRunner)
    engine, store = app.state.engine, app.state.store
    simulated_fleet(engine, store, trucks=5, versions=3, drifting={"DRIFT-1": 0.08}, new_effect="FLEET-002",
                    mapped="MAP-1")
    with TestClient(app) as client:
        client.headers["Authorization"] = "Bearer " + auth.create_token(engine, "engineer")["token"]
        yield client, engine


def test_fleet_summary_finds_the_drifting_truck(fleet):
    client, _ = fleet
    r = client.get("/api/v1/fleet")
    assert r.status_code == 200
    body = r.json()
    assert body["points"] == ["1000x600Nm", "1200x1200Nm", "1400x1800Nm"] and body["threshold_percent"] == 5.0
    trucks = {t["truck"]: t for t in body["trucks"]}
    d = trucks["DRIFT-1"]
    base = (client.get("/api/v1/trucks/DRIFT-1/history").json()["versions"][0]["steady_fuel"] - 2.0) / K
    assert d["steady_fuel"] - 2.0 == pytest.approx(1.08 * base * K, rel=1e-9)  # +8 % above idle, as built
    assert d["drift_percent"] == pytest.approx(100 * 0.08 * base * K / (2.0 + base * K), rel=1e-6)
    assert d["drift_std_percent"] < 0.5 and d["drift_alert"]
    assert [a["kind"] for a in d["alerts"]] == ["drift"]
    assert d["data_hours"] == pytest.approx(10.0) and d["versions"] == 3 and d["latest_version"] == 3
    assert d["fit_percent"] == 92.0 and d["cycle_fuel_error_percent"] == 1.1 and d["unit"] == "L/h"
    for name in ["FLEET-000", "FLEET-001", "FLEET-003", "FLEET-004"]:
        assert abs(trucks[name]["drift_percent"]) < 0.5 and trucks[name]["alerts"] == []
    assert [a["kind"] for a in trucks["FLEET-002"]["alerts"]] == ["new effect"]
    assert trucks["FLEET-002"]["top_effect"] == "fan_on"
    assert body["fleet_median_steady_fuel"] == pytest.approx(statistics.median(t["steady_fuel"] for t in body["trucks"]))
    assert d["vs_fleet_percent"] == pytest.approx(100 * (d["steady_fuel"] / body["fleet_median_steady_fuel"] - 1))


def test_effects_in_the_model_and_missing_each_once_and_the_map_never_alerts(fleet):
    client, _ = fleet
    trucks = {t["truck"]: t for t in client.get("/api/v1/fleet").json()["trucks"]}
    assert trucks["FLEET-002"]["effects"] == [] and trucks["FLEET-002"]["missing_effects"] == ["fan_on"]
    mapped = trucks["MAP-1"]
    assert mapped["effects"] == ["engine_map"] and mapped["missing_effects"] == [] and mapped["alerts"] == []
    assert mapped["steady_fuel"] > 2.0 and mapped["steady_reference"] == {}  # the map needs only speed and torque
    assert abs(mapped["drift_percent"]) < 0.5  # the map is in every version: no spurious drift
    latest = client.get("/api/v1/trucks/MAP-1/history").json()["versions"][-1]
    assert latest["effects"] == ["engine_map"] and latest["missing_effects"] == []
    assert all(a["truck"] != "MAP-1" for a in client.get("/api/v1/alerts").json())


def test_reference_points_and_threshold_per_request(fleet):
    client, _ = fleet
    low = client.get("/api/v1/fleet", params={"points": "800x200Nm", "threshold": 20}).json()
    d = next(t for t in low["trucks"] if t["truck"] == "DRIFT-1")
    assert low["points"] == ["800x200Nm"] and d["per_point"] == [d["steady_fuel"]] and not d["drift_alert"]
    first = 2.0 + (d["steady_fuel"] - 2.0) / 1.08  # the first version's fuel at the one point
    assert d["drift_percent"] == pytest.approx(100 * (d["steady_fuel"] / first - 1), rel=1e-6)
    pct = client.get("/api/v1/fleet", params={"points": "1200x50%"}).json()["trucks"][0]
    assert pct["steady_fuel"] is None and "need rpm and %" in pct["note"]
    bad = client.get("/api/v1/fleet", params={"points": "1200rpm"})
    assert bad.status_code == 422 and "RPMxTORQUE" in bad.json()["detail"]


def by_truck(client, **params) -> dict:
    return {t["truck"]: t for t in client.get("/api/v1/fleet", params=params).json()["trucks"]}


def alerts_of(client, **params) -> list[tuple[str, str, int]]:
    return sorted((a["truck"], a["kind"], a["version"]) for a in client.get("/api/v1/alerts", params=params).json())


@pytest.fixture
def computed(monkeypatch):
    """The trucks whose fleet row the server computes (again), in order."""
    names = []

    def counting(r, *args):
        names.append(r["truck"])
        return truck_summary(r, *args)

    truck_summary = console.truck_summary
    monkeypatch.setattr(console, "truck_summary", counting)
    return names


def test_a_new_version_changes_that_truck_row_and_the_alerts(fleet, computed):
    client, engine = fleet
    store = client.app.state.store
    before = by_truck(client)
    assert client.get("/api/v1/fleet").json()["trucks"] == list(before.values())  # unchanged registry: kept
    assert sorted(computed) == sorted(before) and alerts_of(client) == [("DRIFT-1", "drift", 3),
                                                                         ("FLEET-002", "new effect", 3)]
    computed.clear()
    db.add_model(engine, truck="FLEET-000", job_id=None, metrics={}, **store_version(store, "FLEET-000",
                                                                                     engine_model(1.3)))
    after = by_truck(client)
    assert computed == ["FLEET-000"]  # one truck's row computed again, not the fleet's
    worn = after["FLEET-000"]
    assert worn["latest_version"] == 4 and worn["drift_percent"] > 20 and worn["drift_alert"]
    assert worn["fit_percent"] is None and worn["unit"] == "L/h"  # the new version's (empty) metrics
    assert alerts_of(client) == [("DRIFT-1", "drift", 3), ("FLEET-000", "drift", 4), ("FLEET-002", "new effect", 3)]
    median = statistics.median(t["steady_fuel"] for t in after.values() if t["steady_fuel"] is not None)
    for name, row in after.items():  # every other row as it was, against the new fleet median
        assert row["vs_fleet_percent"] == pytest.approx(100 * (row["steady_fuel"] / median - 1))
        if name != "FLEET-000":
            assert {**row, "vs_fleet_percent": None} == {**before[name], "vs_fleet_percent": None}


def test_new_trucks_and_files_show_however_they_were_committed(fleet, computed):
    client, engine = fleet
    assert by_truck(client)["FLEET-003"]["files"] == 2
    computed.clear()
    for sha, truck in [("ab", "FLEET-003"), ("ef", "A-NEW")]:
        db.add_file(engine, sha256=sha * 32, truck=truck, size_bytes=10, start_ns=0, end_ns=3600 * 10**9, messages=1)
    trucks = by_truck(client)
    assert trucks["FLEET-003"]["files"] == 3 and trucks["FLEET-003"]["data_hours"] == pytest.approx(11.0)
    assert trucks["A-NEW"]["note"] == "no model yet" and list(trucks)[0] == "A-NEW"  # by name
    assert sorted(computed) == ["A-NEW", "FLEET-003"]
    with engine.begin() as conn:  # a file whose upload time is older than the newest seen (committed late)
        conn.execute(db.files.insert().values(sha256="cd" * 32, truck="FLEET-004", size_bytes=1, messages=1,
                                              start_ns=0, end_ns=3600 * 10**9, uploaded_unix_s=1.0))
    f = by_truck(client)["FLEET-004"]
    assert f["files"] == 3 and f["data_hours"] == pytest.approx(11.0)


def test_a_new_effect_alerts_once(fleet):
    client, engine = fleet
    store = client.app.state.store
    def named(effect):
        db.add_model(engine, truck="FLEET-001", job_id=None, metrics={}, top_effect=effect,
                     **store_version(store, "FLEET-001", engine_model(1.0), effect))

    named("fan_on")
    assert ("FLEET-001", "new effect", 4) in alerts_of(client)
    named("fan_on")  # named again by version 5: no longer new
    assert by_truck(client)["FLEET-001"]["top_effect"] == "fan_on"
    assert [a for a in alerts_of(client) if a[0] == "FLEET-001"] == []


def test_points_and_threshold_have_their_own_rows(fleet, computed):
    client, engine = fleet
    store = client.app.state.store
    default, low = by_truck(client), by_truck(client, points="800x200Nm")
    assert low["DRIFT-1"]["steady_fuel"] < default["DRIFT-1"]["steady_fuel"]  # computed at the other point
    assert computed.count("DRIFT-1") == 2
    assert ("DRIFT-1", "drift", 3) not in alerts_of(client, threshold=20)  # +8 % of the fuel above idle
    assert ("DRIFT-1", "drift", 3) in alerts_of(client, threshold=5)
    db.add_model(engine, truck="DRIFT-1", job_id=None, metrics={}, **store_version(store, "DRIFT-1",
                                                                                   engine_model(0.5)))
    computed.clear()
    for params in [{"points": "800x200Nm"}, {}]:  # each choice sees the new version (nothing stale)
        d = by_truck(client, **params)["DRIFT-1"]
        assert d["latest_version"] == 4 and d["drift_percent"] < -10 and d["drift_alert"]
    assert computed == ["DRIFT-1", "DRIFT-1"]


def test_deleted_versions_and_trucks_leave_the_view(fleet):
    """The API deletes nothing; an operator's DELETE in the database shows all the same."""
    client, engine = fleet
    assert by_truck(client)["FLEET-002"]["latest_version"] == 3
    m = db.models.c
    with engine.begin() as conn:  # not the newest row of the registry: DRIFT-1's versions came after
        conn.execute(db.models.delete().where((m.truck == "FLEET-002") & (m.version == 3)))
    f = by_truck(client)["FLEET-002"]
    assert f["latest_version"] == 2 and f["versions"] == 2 and f["top_effect"] is None
    assert alerts_of(client) == [("DRIFT-1", "drift", 3)]
    with engine.begin() as conn:
        conn.execute(db.models.delete().where(m.truck == "DRIFT-1"))
        conn.execute(db.files.delete().where(db.files.c.truck == "DRIFT-1"))
        conn.execute(db.trucks.delete().where(db.trucks.c.truck == "DRIFT-1"))
    assert "DRIFT-1" not in by_truck(client) and alerts_of(client) == []


def fingerprint(conn) -> tuple:
    return tuple(conn.execute(console.FINGERPRINT).one())


def test_only_trucks_with_new_rows_are_read_again(fleet):
    client, engine = fleet
    store = client.app.state.store
    with engine.connect() as conn:
        before = fingerprint(conn)
    db.add_model(engine, truck="FLEET-000", job_id=None, metrics={}, **store_version(store, "FLEET-000",
                                                                                     engine_model(1.0)))
    db.add_file(engine, sha256="ab" * 32, truck="FLEET-003", size_bytes=10, start_ns=0, end_ns=10**9, messages=1)
    db.add_file(engine, sha256="ef" * 32, truck="NEW-1", size_bytes=10, start_ns=0, end_ns=10**9, messages=1)
    with engine.connect() as conn:
        assert console.trucks_added_to(conn, before, fingerprint(conn)) == {"FLEET-000", "FLEET-003", "NEW-1"}
    for change in [  # what new rows do not account for: every truck is read again
            db.models.delete().where((db.models.c.truck == "FLEET-001") & (db.models.c.version == 2)),
            db.files.insert().values(sha256="cd" * 32, truck="FLEET-001", size_bytes=1, messages=1,
                                     uploaded_unix_s=1.0),  # committed late with an old upload time
            db.trucks.insert().values(truck="NEW-2", created_unix_s=1.0)]:
        with engine.connect() as conn:
            before = fingerprint(conn)
        with engine.begin() as conn:
            conn.execute(change)
        with engine.connect() as conn:
            assert console.trucks_added_to(conn, before, fingerprint(conn)) is None


def test_a_view_holds_one_row_per_truck(fleet):
    client, engine = fleet
    view = console.FleetView(console.DEFAULT_POINTS, 5.0)
    cache = console.ModelCache(client.app.state.store)
    with engine.connect() as conn:
        view.refresh(conn, cache, fingerprint(conn))
    assert sorted(view.rows) == ["DRIFT-1", "FLEET-000", "FLEET-001", "FLEET-002", "FLEET-003", "FLEET-004", "MAP-1"]
    with engine.begin() as conn:
        conn.execute(db.models.delete().where(db.models.c.truck == "FLEET-004"))
        conn.execute(db.files.delete().where(db.files.c.truck == "FLEET-004"))
        conn.execute(db.trucks.delete().where(db.trucks.c.truck == "FLEET-004"))
    with engine.connect() as conn:
        view.refresh(conn, cache, fingerprint(conn))
    assert sorted(view.rows) == ["DRIFT-1", "FLEET-000", "FLEET-001", "FLEET-002", "FLEET-003", "MAP-1"]


def test_alerts_and_history(fleet):
    client, _ = fleet
    alerts = client.get("/api/v1/alerts").json()
    assert sorted((a["truck"], a["kind"]) for a in alerts) == [("DRIFT-1", "drift"), ("FLEET-002", "new effect")]
    h = client.get("/api/v1/trucks/DRIFT-1/history").json()
    assert [v["version"] for v in h["versions"]] == [1, 2, 3]
    assert h["versions"][0]["drift_percent"] is None and h["versions"][1]["drift_percent"] == pytest.approx(
        h["versions"][2]["drift_percent"] / 2, rel=0.02)  # half the drift at the middle version
    assert all(v["has_report"] for v in h["versions"]) and len(h["files"]) == 2
    assert client.get("/api/v1/trucks/NOPE/history").status_code == 404


def test_report_link_works_without_a_token_for_a_while(fleet):
    client, _ = fleet
    link = client.post("/api/v1/trucks/DRIFT-1/models/2/report-link").json()
    assert link["url"].startswith("/reports/")
    r = client.get(link["url"], headers={"Authorization": ""})
    assert r.status_code == 200 and "DRIFT-1" in r.text
    assert "sandbox allow-scripts" in r.headers["content-security-policy"]
    assert client.get("/reports/" + "x" * 32).status_code == 404
    assert client.post("/api/v1/trucks/DRIFT-1/models/9/report-link").status_code == 404


def test_page_and_roles(fleet):
    client, engine = fleet
    page = client.get("/", headers={"Authorization": ""})
    assert page.status_code == 200 and '<script src="/static/console.js"' in page.text
    csp = page.headers["content-security-policy"]
    assert "script-src 'self'" in csp and "unsafe-inline" not in csp and "default-src 'none'" in csp
    js = client.get("/static/console.js", headers={"Authorization": ""})
    assert js.status_code == 200 and "innerHTML" not in js.text and "localStorage" not in js.text
    assert client.get("/api/v1/fleet", headers={"Authorization": ""}).status_code == 401
    truck = auth.create_token(engine, "truck", "DRIFT-1")["token"]
    assert client.get("/api/v1/alerts", headers={"Authorization": f"Bearer {truck}"}).status_code == 403
    paths = client.get("/openapi.json").json()["paths"]
    for p in ["/api/v1/fleet", "/api/v1/alerts", "/api/v1/trucks/{truck}/history",
              "/api/v1/trucks/{truck}/models/{version}/report-link", "/reports/{ticket}"]:
        assert p in paths
