"""Reading VECTO engine sets: the shipped 325 kW engine, and a clear one-line error for each broken set."""
import json
import shutil

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.sim.vecto import engine_file, read_engine


@pytest.fixture
def engine_set(tmp_path):
    """A writable copy of the shipped set; returns the path of its .veng file."""
    src = engine_file("vecto_325kW").parent
    for f in src.iterdir():
        shutil.copy(f, tmp_path / f.name)
    return tmp_path / "Engine_325kW_12.7l.veng"


def test_the_shipped_engine_by_its_short_name():
    e = read_engine("vecto_325kW")
    assert e.idle_speed_rpm == 600.0 and e.inertia_kgm2 == pytest.approx(5.1498)
    assert e.displacement_cm3 == 12740.0 and e.whtc == {"urban": 1.04, "rural": 1.01, "motorway": 1.0}
    assert e.max_torque_nm == 2134.0 and len(e.map_rpm) == 106 and e.pt1_s is None
    assert e.full_load(1200.0) == 2134.0 and e.motoring(1000.0) == -152.0


def test_a_set_read_by_its_path_equals_the_shipped_one(engine_set):
    for f in engine_set.parent.iterdir():  # as VECTO writes them on Windows: a byte-order mark, CR LF
        f.write_bytes(b"\xef\xbb\xbf" + f.read_bytes().replace(b"\n", b"\r\n"))
    e = read_engine(engine_set)
    np.testing.assert_array_equal(e.map_g_h, read_engine("vecto_325kW").map_g_h)


def test_the_map_is_reproduced_at_its_points_and_zero_when_motoring():
    e = read_engine("vecto_325kW")
    inside = e.map_nm <= e.full_load(e.map_rpm)  # a few top points lie 1-2 Nm above the .vfld curve
    np.testing.assert_allclose(e.fuel_g_h(e.map_rpm[inside], e.map_nm[inside]), e.map_g_h[inside], rtol=1e-9)
    assert np.all(e.fuel_g_h([800.0, 1500.0, 2000.0], [-400.0, -250.0, -279.0]) == 0.0)
    # between points: linear on the triangulation, so between its neighbours; above full load: held at full load
    f = e.fuel_g_h(1100.0, 1000.0)
    assert 18443 < f < 26164  # the map at (1000 | 1200 rpm, 928 | 1114 Nm)
    assert e.fuel_g_h(1200.0, 3000.0) == pytest.approx(e.fuel_g_h(1200.0, 2134.0))


def test_fuel_grows_with_torque_and_speed_across_the_map():
    e = read_engine("vecto_325kW")
    n, t = np.meshgrid(np.arange(650.0, 2100.0, 50.0), np.arange(0.0, 2100.0, 50.0))
    t = np.minimum(t, e.full_load(n))
    f = e.fuel_g_h(n, t)
    assert np.all(np.isfinite(f)) and np.all(np.diff(f, axis=0) >= -1e-6)


def _edit_json(path, **changes):
    doc = json.loads(path.read_text())
    for k, v in changes.items():
        if v is None:
            del doc["Body"][k]
        else:
            doc["Body"][k] = v
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("edit, message", [
    (lambda p: p.write_text("{ not json"), "not a VECTO engine file (JSON)"),
    (lambda p: p.write_text("[]"), "no \"Body\" object"),
    (lambda p: _edit_json(p, IdlingSpeed=None), "field 'IdlingSpeed' missing"),
    (lambda p: _edit_json(p, FuelMap=None), "field 'FuelMap' missing"),
    (lambda p: _edit_json(p, Inertia="heavy"), "field 'Inertia' is not a number: 'heavy'"),
    (lambda p: _edit_json(p, IdlingSpeed=-600), "field 'IdlingSpeed' = -600 is outside"),
    (lambda p: _edit_json(p, FullLoadCurve="missing.vfld"), "field 'FullLoadCurve' names"),
    (lambda p: _edit_json(p, FuelMap=""), "field 'FuelMap' must name a file"),
    (lambda p: _edit_json(p, IdlingSpeed=500.0), "IdlingSpeed 500 rpm is below the full-load curve's first speed"),
])
def test_a_broken_engine_file_is_one_line_naming_the_field(engine_set, edit, message):
    edit(engine_set)
    with pytest.raises(FuelidError, match=None) as err:
        read_engine(engine_set)
    text = str(err.value)
    assert message in text and str(engine_set) in text and "\n" not in text


def _replace_line(path, number, line):
    lines = path.read_text().splitlines()
    lines[number - 1] = line
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("file, edit, message", [
    ("325kW.vmap", lambda p: _replace_line(p, 3, "600,abc,1355"), "line 3: not a number"),
    ("325kW.vmap", lambda p: _replace_line(p, 4, "600,186"), "line 4: expected 3 columns"),
    ("325kW.vmap", lambda p: _replace_line(p, 4, "600,0,1355"), "the point 600 rpm, 0 Nm appears twice"),
    ("325kW.vmap", lambda p: _replace_line(p, 5, "600,371,-5"), "fuel consumption [g/h] is negative"),
    ("325kW.vmap", lambda p: p.write_text("engine speed,torque,fuel\n"), "fewer than two rows"),
    ("325kW.vmap", lambda p: p.write_text("n,T,f\n600,0,1\n800,0,2\n1000,0,3\n"), "span no area"),
    ("325kW.vmap", lambda p: p.write_text(""), "empty"),
    ("325kW.vfld", lambda p: _replace_line(p, 3, "600,1200,-138"), "must increase"),
    ("325kW.vfld", lambda p: _replace_line(p, 11, "672,1358.28,12"), "motoring torque [Nm] must be <= 0"),
    ("325kW.vfld", lambda p: _replace_line(p, 11, "672,-5,-139"), "full load torque [Nm] is negative"),
    ("325kW.vfld", lambda p: _replace_line(p, 11, "672,1358.28"), "line 11: expected 3 columns"),
    ("325kW.vfld", lambda p: _replace_line(p, 11, "672,nan,-139"), "not a finite number"),
])
def test_a_broken_map_or_curve_is_one_line_naming_the_file_and_field(engine_set, file, edit, message):
    edit(engine_set.parent / file)
    with pytest.raises(FuelidError) as err:
        read_engine(engine_set)
    text = str(err.value)
    assert message in text and file in text and "\n" not in text


def test_a_pt1_column_is_read_per_speed(engine_set):
    fld = engine_set.parent / "325kW.vfld"
    lines = fld.read_text().splitlines()
    fld.write_text("\n".join([lines[0] + ", PT1 [s]"] + [f"{s},{0.5 + i * 0.001:g}" for i, s in enumerate(lines[1:])])
                   + "\n")
    e = read_engine(engine_set)
    assert e.pt1_s is not None and e.pt1(600.0) == pytest.approx(0.5)


def test_an_unknown_name_lists_the_shipped_engines(tmp_path):
    with pytest.raises(FuelidError, match="vecto_325kW"):
        read_engine(tmp_path / "nothing.veng")
