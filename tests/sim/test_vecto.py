"""Reading VECTO engine sets: the shipped 325 kW engine, every set in ../shared/engines, small FileVersion 5 sets
(one fuel, dual fuel, non-rectangular maps), and a clear one-line error for each broken set."""
import json
import shutil

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.sim.vecto import describe, engine_file, read_engine
from tests.sim.conftest import SHARED_ENGINES as SHARED


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
    (lambda p: _edit_json(p, FullLoadCurve=None), "field 'FullLoadCurve' missing"),
    (lambda p: _edit_json(p, FuelMap=""), "field 'FuelMap' must name a file"),
    (lambda p: _edit_json(p, IdlingSpeed=500.0), "IdlingSpeed 500 rpm is below the full-load curve's first speed"),
])
def test_a_broken_engine_file_is_one_line_naming_the_field(engine_set, edit, message):
    edit(engine_set)
    with pytest.raises(FuelidError, match=None) as err:
        read_engine(engine_set)
    text = str(err.value)
    assert message in text and str(engine_set) in text and "\n" not in text


def _as_file_version_2(veng, curves):
    """The set rewritten as VECTO 2 wrote it: FileVersion 2, the curve in FullLoadCurves, WHTC fields in g/kWh."""
    doc = json.loads(veng.read_text())
    doc["Header"]["FileVersion"] = 2
    doc["Body"]["FullLoadCurves"] = curves(doc["Body"].pop("FullLoadCurve"))
    doc["Body"].update({"WHTC-Urban": 214.0, "WHTC-Rural": 196.0, "WHTC-Motorway": 188.0})
    veng.write_text(json.dumps(doc))


def test_a_file_version_2_set_reads_its_engine_curve_as_vecto_does(engine_set):
    shipped = read_engine(engine_set)
    _as_file_version_2(engine_set, lambda vfld: [{"Path": vfld, "Gears": "0 - 99"},
                                                 {"Path": "none.vfld", "Gears": "1"}])  # a gear's: not read
    e = read_engine(engine_set)
    assert e.file_version == 2 and e.whtc == {"urban": 1.0, "rural": 1.0, "motorway": 1.0}  # VECTO 2 reads none
    assert np.array_equal(e.full_load_nm, shipped.full_load_nm) and np.array_equal(e.map_g_h, shipped.map_g_h)


@pytest.mark.parametrize("curves, message", [(lambda vfld: vfld, "field 'FullLoadCurves' must list objects"),
                                             (lambda vfld: [{"Path": "none.vfld"}], "field 'Path' names")])
def test_a_broken_file_version_2_curve_is_one_line(engine_set, curves, message):
    _as_file_version_2(engine_set, curves)
    with pytest.raises(FuelidError) as err:
        read_engine(engine_set)
    assert message in str(err.value) and "\n" not in str(err.value)


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


def test_every_shared_engine_set_reads_and_its_map_is_reproduced(shared_engine):
    e = read_engine(shared_engine)
    assert e.fuel_type == "DieselCI" and e.fuels == ("DieselCI",) and e.fuel_density_kg_l == pytest.approx(0.835)
    assert 150.0 < e.rated_power_kw < 400.0 and e.fld_rpm[0] <= e.idle_speed_rpm < e.rated_speed_rpm
    inside = (e.map_nm <= e.full_load(e.map_rpm)) & (e.map_nm > e.motoring(e.map_rpm))
    np.testing.assert_allclose(e.fuel_g_h(e.map_rpm[inside], e.map_nm[inside]), e.map_g_h[inside], rtol=1e-9)
    # up to rated speed: above it the 220 kW map thins out to two points at 2600 rpm, where linear interpolation on
    # long thin triangles need not grow with torque
    n, t = np.meshgrid(np.linspace(e.idle_speed_rpm, e.rated_speed_rpm, 40), np.linspace(0.0, e.max_torque_nm, 40))
    f = e.fuel_g_h(n, np.minimum(t, e.full_load(n)))
    assert np.all(np.isfinite(f)) and np.all(np.diff(f, axis=0) >= -1e-6)  # fuel grows with torque
    assert np.all(e.fuel_g_h(n[0], e.motoring(n[0]) - 1.0) == 0.0)


def test_the_220kW_set_declares_its_rated_power_and_names_its_fuel():
    veng = SHARED / "vecto_220kW_7.7l" / "Engine_220kW.veng"
    if not veng.is_file():
        pytest.skip(f"VECTO engine sets not available ({veng.parent})")
    e = read_engine(veng)
    assert (e.rated_power_kw, e.rated_speed_rpm, e.max_torque_nm) == (220.0, 2200.0, 1200.0)
    assert e.pt1_s is None and e.file_version == 4 and e.displacement_cm3 == 7700.0
    assert describe(e)["fuel_type"] == "DieselCI" and "fuels_note" not in describe(e)


def test_a_set_without_rated_power_takes_it_from_the_full_load_curve():
    e = read_engine("vecto_325kW")  # FileVersion 3: no RatedPower, RatedSpeed, MaxTorque
    power_kw = e.full_load_nm * e.fld_rpm * np.pi / 30.0 / 1000.0
    assert e.rated_power_kw == pytest.approx(power_kw.max()) and 300.0 < e.rated_power_kw < 340.0
    assert e.rated_speed_rpm == e.fld_rpm[np.argmax(power_kw)]


FLD = "engine speed [rpm],full load torque [Nm],motoring torque [Nm]\n600,500,-40\n1000,900,-55\n1800,800,-80\n2200,600,-100\n"
"""A small full-load curve: the map below is cut by it (600 rpm: up to 500 Nm; 1000 rpm: up to 900 Nm)."""


def _non_rectangular_map() -> str:
    rows = ["engine speed [rpm],torque [Nm],fuel consumption [g/h]"]
    for n, t_max in ((600, 500), (1000, 900), (1400, 850), (1800, 800), (2200, 600)):
        rows.append(f"{n},{-40 - 0.03 * (n - 600):g},0")
        for t in range(0, t_max + 1, 100):
            rows.append(f"{n},{t},{600 + 0.5 * n + 0.2 * t * (1 + n / 2000) + 1e-4 * t * t:g}")
    return "\n".join(rows) + "\n"


def _v5(tmp_path, fuels, body=None, bom=True):
    """A FileVersion 5 set in tmp_path (a BOM and CR LF as VECTO writes on Windows); returns the .veng path."""
    def write(name, text):
        data = text.replace("\n", "\r\n").encode()
        (tmp_path / name).write_bytes((b"\xef\xbb\xbf" if bom else b"") + data)

    write("e.vfld", FLD)
    write("diesel.vmap", _non_rectangular_map())
    write("gas.vmap", _non_rectangular_map())
    doc = {"Header": {"FileVersion": 5},
           "Body": {"ModelName": "synthetic v5", "IdlingSpeed": 600.0, "Inertia": 3.0, "Displacement": 7000,
                    "RatedPower": 0.0, "RatedSpeed": 0.0, "MaxTorque": 0.0, "FullLoadCurve": "e.vfld",
                    "Fuels": fuels, **(body or {})}}
    write("e.veng", json.dumps(doc, indent=2))
    return tmp_path / "e.veng"


DIESEL = {"FuelMap": "diesel.vmap", "FuelType": "DieselCI", "WHTC-Urban": 1.02, "WHTC-Rural": 1.01,
          "WHTC-Motorway": 1.0, "ColdHotBalancingFactor": 1.0, "CFRegPer": 1.0}


def test_a_file_version_5_set_reads_its_first_fuel_and_the_curve_gives_the_ratings(tmp_path):
    e = read_engine(_v5(tmp_path, [DIESEL]))
    assert e.file_version == 5 and e.fuel_type == "DieselCI" and e.whtc == {"urban": 1.02, "rural": 1.01,
                                                                           "motorway": 1.0}
    assert e.max_torque_nm == 900.0 and e.rated_power_kw == pytest.approx(800.0 * 1800.0 * np.pi / 30.0 / 1000.0)
    # the non-rectangular grid: between its points linear, above the full-load line held there, 0 when motoring
    assert 600 + 0.5 * 1000 + 0.2 * 400 * 1.5 < e.fuel_g_h(1000.0, 450.0) < 600 + 0.5 * 1000 + 0.2 * 500 * 1.5 + 50
    assert e.fuel_g_h(600.0, 800.0) == pytest.approx(e.fuel_g_h(600.0, 500.0))
    assert e.fuel_g_h(1400.0, -100.0) == 0.0


def test_a_dual_fuel_set_uses_its_primary_fuel_and_says_so(tmp_path):
    gas = {**DIESEL, "FuelMap": "gas.vmap", "FuelType": "NGCI", "WHTC-Urban": 1.05}
    e = read_engine(_v5(tmp_path, [DIESEL, gas]))
    assert e.fuels == ("DieselCI", "NGCI") and e.whtc["urban"] == 1.02
    d = describe(e)
    assert d["fuels"] == ["DieselCI", "NGCI"] and "primary fuel DieselCI" in d["fuels_note"]


@pytest.mark.parametrize("fuel_type, name, density", [(0, "DieselCI", 0.835), ("2", "PetrolPI", 0.748),
                                                      ("ethanolci", "EthanolCI", 0.820)])
def test_a_fuel_type_by_number_or_name_sets_the_density(tmp_path, fuel_type, name, density):
    e = read_engine(_v5(tmp_path, [{**DIESEL, "FuelType": fuel_type}]))
    assert e.fuel_type == name and e.fuel_density_kg_l == density


def test_a_file_version_4_fuel_type_is_read_beside_the_map(engine_set):
    _edit_json(engine_set, FuelType="PetrolPI")
    assert read_engine(engine_set).fuel_type == "PetrolPI"


def test_a_gaseous_primary_fuel_has_no_litres_to_report(tmp_path):
    e = read_engine(_v5(tmp_path, [{**DIESEL, "FuelType": "NGPI"}]))
    with pytest.raises(FuelidError, match="fuel type NGPI is a gas") as err:
        e.fuel_density_kg_l
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("fuels, body, message", [
    ([], None, "field 'Fuels' must be a list of fuel objects"),
    ("diesel.vmap", None, "field 'Fuels' must be a list of fuel objects"),
    ([{"FuelType": "DieselCI"}], None, "field 'Fuels[0].FuelMap' missing"),
    ([DIESEL, {"FuelMap": "gas.vmap"}], None, "field 'Fuels[1].FuelType' missing"),
    ([{**DIESEL, "FuelType": "Kerosene"}], None, "field 'FuelType' = 'Kerosene' is not a VECTO fuel type"),
    ([{**DIESEL, "FuelType": 9}], None, "field 'FuelType' = 9 is not a VECTO fuel type"),
    ([{**DIESEL, "FuelMap": "none.vmap"}], None, "field 'FuelMap' names"),
    ([{**DIESEL, "WHTC-Urban": "high"}], None, "field 'WHTC-Urban' is not a number"),
    ([DIESEL], {"RatedPower": -5}, "field 'RatedPower' = -5 is outside"),
])
def test_a_broken_file_version_5_set_is_one_line_naming_the_field(tmp_path, fuels, body, message):
    veng = _v5(tmp_path, fuels, body)
    with pytest.raises(FuelidError) as err:
        read_engine(veng)
    assert message in str(err.value) and str(veng) in str(err.value) and "\n" not in str(err.value)


def test_a_comma_before_a_closing_bracket_is_read_as_vecto_reads_it(tmp_path):
    veng = _v5(tmp_path, [DIESEL], {"ModelName": "one, } two"}, bom=False)  # a string that looks like one stays
    veng.write_bytes(veng.read_bytes().replace(b'"CFRegPer": 1.0', b'"CFRegPer": 1.0,')
                     .rstrip().removesuffix(b"}") + b",\r\n}")
    e = read_engine(veng)
    assert e.fuel_type == "DieselCI" and e.name == "one, } two"


def test_engineering_mode_factors_stand_in_for_declaration_factors_left_at_zero(tmp_path):
    zero = {**DIESEL, "WHTC-Urban": 0.0, "WHTC-Rural": 0.0, "WHTC-Motorway": 0.0}
    e = read_engine(_v5(tmp_path, [{**zero, "WHTC-Engineering": 1.03}]))
    assert e.whtc == {"urban": 1.03, "rural": 1.03, "motorway": 1.03}
    assert read_engine(_v5(tmp_path, [{**zero, "WHTC-Engineering": 0.0}])).whtc["urban"] == 1.0
    with pytest.raises(FuelidError, match="field 'WHTC-Engineering' = 0.5 is outside 0.8..1.5"):
        read_engine(_v5(tmp_path, [{**zero, "WHTC-Engineering": 0.5}]))


def test_map_columns_are_found_by_their_header_and_further_columns_are_not_read(tmp_path):
    veng = _v5(tmp_path, [DIESEL], bom=False)
    plain = read_engine(veng)
    rows = [line.split(",") for line in _non_rectangular_map().splitlines()]
    # a waste-heat-recovery engine's map: a column more; and the same columns in another order
    (tmp_path / "diesel.vmap").write_text("\n".join(",".join(r + ["whr power electrical [W]" if k == 0 else "0"])
                                                    for k, r in enumerate(rows)) + "\n")
    np.testing.assert_array_equal(read_engine(veng).map_g_h, plain.map_g_h)
    (tmp_path / "diesel.vmap").write_text("\n".join(",".join([r[2], r[0], r[1]]) for r in rows) + "\n")
    e = read_engine(veng)
    np.testing.assert_array_equal(e.map_g_h, plain.map_g_h)
    np.testing.assert_array_equal(e.map_rpm, plain.map_rpm)
    # a header with a name more than the rows have columns does not name them: the first three are read
    lines = [",".join(["point", *rows[0]])] + [",".join(r) for r in rows[1:]]
    (tmp_path / "diesel.vmap").write_text("\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_engine(veng).map_g_h, plain.map_g_h)
