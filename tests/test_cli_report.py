"""fuelid report end to end: the README's loop on a short simulated trip with a DPF regeneration (simulate, convert,
identify without and with the effect, report), and the page rendered by headless Chromium — Debian's chromium,
which .ci/chromium-setup installs — with no console errors, no network request and a screenshot that shows plots."""
import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fuelid.cli import main
from fuelid.commands.report import truck_name

CHROMIUM = Path("/usr/bin/chromium")
ORDERS = "nb=2,2;nf=1,1;nk=1,0;nc=1;nd=1"
BEFORE_BLUE = (0x1F, 0x77, 0xB4)  # ident.report.COLOURS[0], the model's curves


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """A directory with trip.mcap (10 min urban, DPF regeneration +20 % in its middle half), before.json, after.json
    (refitted with effect dpf_regeneration) and report.html."""
    d = tmp_path_factory.mktemp("report")
    steps = [
        ["simulate", "--truth", "diesel_p320", "--cycle", "urban", "--duration", "600", "--seed", "5",
         "--effect", "dpf_regeneration=0.2", "-o", str(d / "trip.log.gz")],
        ["convert", str(d / "trip.log.gz"), "-o", str(d / "trip.mcap")],
        ["identify", str(d / "trip.mcap"), "--orders", ORDERS, "-o", str(d / "before.json")],
        ["identify", str(d / "trip.mcap"), "--orders", ORDERS, "--effect", "dpf_regeneration", "-o",
         str(d / "after.json")],
        ["report", str(d / "before.json"), str(d / "after.json"), str(d / "trip.mcap"), "-o", str(d / "report.html"),
         "--title", "Urban trip", "--builds", "1"],
    ]
    for argv in steps:
        assert main(argv) == 0, argv
    return d


def test_report_command_writes_one_offline_page(loop, capsys):
    page = (loop / "report.html").read_text(encoding="utf-8")
    truck = truck_name([loop / "trip.mcap"])
    assert truck and len(truck) == 17  # the simulator's VIN, from the MCAP metadata
    assert "<title>Urban trip</title>" in page and f"<td>{truck}</td>" in page
    assert re.search(r"after\.json: RMS error fell from \d+\.\d\d to \d+\.\d\d L/h; cycle fuel error from "
                     r"[+-]\d+\.\d\d % to [+-]\d+\.\d\d %", page)
    assert "dpf_regeneration" in page and "DPF active regeneration" in page
    assert "<script src" not in page and "<link" not in page  # one file: scripts and styles inline


def test_report_reuses_a_saved_diagnosis(loop, tmp_path, capsys):
    before, trip = str(loop / "before.json"), str(loop / "trip.mcap")
    assert main(["diagnose", before, trip, "--builds", "1", "--json"]) == 0
    saved = tmp_path / "diagnosis.json"
    saved.write_text(capsys.readouterr().out)
    page = tmp_path / "r.html"
    assert main(["report", before, trip, "--diagnosis", str(saved), "-o", str(page)]) == 0
    assert json.loads(saved.read_text())["verdict"] in capsys.readouterr().out
    assert "DPF active regeneration" in page.read_text(encoding="utf-8")
    after = str(loop / "after.json")  # a diagnosis of another model is refused, not mixed into the page
    assert main(["report", after, trip, "--diagnosis", str(saved), "-o", str(tmp_path / "x.html")]) == 1
    err = capsys.readouterr().err
    assert "it diagnosed" in err and len(err.strip().splitlines()) == 1


def test_report_bad_inputs_are_one_line_errors(loop, tmp_path, capsys):
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    for argv, words in [
        (["report", str(loop / "before.json"), "-o", str(tmp_path / "r.html")], "give a model file"),
        (["report", str(loop / "trip.mcap"), "-o", str(tmp_path / "r.html")], "give a model file"),
        (["report", str(broken), str(loop / "trip.mcap"), "-o", str(tmp_path / "r.html")], "broken.json"),
        (["report", str(loop / "before.json"), str(tmp_path / "none.mcap"), "-o", str(tmp_path / "r.html")],
         "no such file"),
        (["report", str(loop / "before.json"), str(loop / "trip.mcap"), "-o", str(tmp_path / "r.html"),
          "--max-points", "10"], "--max-points"),
    ]:
        capsys.readouterr()
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r.html").exists()


def chromium(page: Path, tmp: Path, height: int = 2600) -> dict:
    """Load `page` in headless Chromium with a throwaway profile and name resolution blocked (nothing can leave
    the machine): its DOM after scripts ran, the console messages, the URLs the page requested from the network
    (Chromium's net log; the browser's own background requests are not the page's) and a screenshot."""
    net, png = tmp / "net.json", tmp / "shot.png"
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp / 'profile'}", "--enable-logging=stderr", "--v=0",
           "--host-resolver-rules=MAP * ~NOTFOUND", f"--log-net-log={net}", "--hide-scrollbars",
           f"--window-size=1400,{height}", "--virtual-time-budget=15000", "--dump-dom", f"--screenshot={png}",
           page.resolve().as_uri()]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    log = json.loads(net.read_text())
    start = log["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
    requested = [e["params"]["url"] for e in log["events"] if e["type"] == start
                 and e["params"].get("network_isolation_key", "").startswith("file://")]
    return {"dom": out.stdout, "console": re.findall(r":CONSOLE[:(]\d+\)?\] (.*)", out.stderr),
            "requested": [u for u in requested if not u.startswith(("file:", "data:", "blob:"))], "png": png}


needs_chromium = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed "
                                    "(/usr/bin/chromium; bash .ci/chromium-setup installs it)")


@needs_chromium
def test_chromium_check_sees_console_errors_and_fetches(tmp_path):
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><img src="https://example.com/x.png"><script>console.error("boom"); nope();'
                   '</script>')
    seen = chromium(bad, tmp_path)
    assert any("boom" in m for m in seen["console"]) and any("nope is not defined" in m for m in seen["console"])
    assert seen["requested"] == ["https://example.com/x.png"]


@needs_chromium
def test_report_renders_in_headless_chromium(loop, tmp_path):
    from PIL import Image

    seen = chromium(loop / "report.html", tmp_path)
    assert seen["console"] == [] and seen["requested"] == []
    plots = re.findall(r'<div id="(fig-[\w-]+)" class="plotly-graph-div js-plotly-plot"', seen["dom"])
    assert plots == ["fig-time", "fig-residual", "fig-autocorr", "fig-crosscorr0", "fig-crosscorr1", "fig-map_bias",
                     "fig-map_rms", "fig-effect0"]  # plotly.js drew every figure (it adds js-plotly-plot)
    assert seen["dom"].count('class="main-svg"') >= 2 * len(plots)

    img = np.asarray(Image.open(seen["png"]).convert("RGB")).astype(int)
    assert img.shape[:2] == (2600, 1400)
    non_white = (img < 235).any(axis=2).mean()
    colours = len(np.unique(img.reshape(-1, 3) // 8, axis=0))
    blue = (np.abs(img - BEFORE_BLUE).sum(axis=2) < 40).sum()  # the model's curves drawn in the top plots
    assert non_white > 0.05 and colours > 100 and blue > 500, (non_white, colours, blue)
