"""The console in a real browser: Debian's headless Chromium driven by Playwright against `fuelid serve` (the
stand-in job runner) over a simulated fleet whose truck DRIFT-1 burns 8 % more above idle than its first model.
Signs in, finds that truck at the top of the fleet sorted by drift, opens its report, starts a refit and follows
the job; no console error, no request off the server's origin, a hostile truck name shown as text, the token in
session storage only, and screenshots that are not blank. The sign-in works from the keyboard alone (focus on the
token, Enter signs in, a visible focus ring) and its error reads at WCAG AA contrast; a truck whose model carries
the engine map shows it "in the model", never "missing", and never alerts for it. SQLite and PostgreSQL (the `database` fixture)."""
import time
from pathlib import Path

import pytest

from fuelid.fleet import db
from fuelid.fleet.storage import BlobStore
from tests.fleet.conftest import Server
from tests.fleet.simulated_fleet import simulated_fleet

playwright = pytest.importorskip("playwright.sync_api", reason="pip install playwright (the test extra)")
CHROMIUM = next((p for p in (Path("/usr/lib/chromium/chromium"), Path("/usr/bin/chromium")) if p.exists()), None)
HOSTILE = "<img src=/x onerror=alert(1)>"
# WCAG 2 contrast ratio of an element's text colour and the first opaque background behind it
CONTRAST = """(selector) => {
  const channels = (c) => c.match(/[0-9.]+/g).map(Number);
  const luminance = (c) => {
    const [r, g, b] = channels(c).slice(0, 3).map((v) => v / 255).map(
      (v) => (v <= 0.03928 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4)));
    return 0.2126 * r + 0.7152 * g + 0.0722 * b;
  };
  const node = document.querySelector(selector);
  let back = "rgb(255, 255, 255)";
  for (let n = node; n; n = n.parentElement) {
    const c = getComputedStyle(n).backgroundColor;
    if (channels(c).length === 3 || channels(c)[3] > 0) { back = c; break; }
  }
  const [hi, lo] = [luminance(getComputedStyle(node).color), luminance(back)].sort((x, y) => y - x);
  return (hi + 0.05) / (lo + 0.05);
}"""


def not_blank(png: Path) -> bool:
    """More than a handful of colours and some spread: something was drawn."""
    from PIL import Image, ImageStat

    img = Image.open(png).convert("RGB")
    return len(img.getcolors(1 << 20) or []) > 20 and max(ImageStat.Stat(img).stddev) > 10


@pytest.fixture
def console_server(tmp_path, database):
    s = Server(tmp_path / "data", database)
    simulated_fleet(s.engine, BlobStore(s.data_dir), trucks=8, versions=3, drifting={"DRIFT-1": 0.08}, mapped="MAP-1")
    with s.engine.begin() as conn:  # a name no upload could give (the API refuses it), straight into the registry
        conn.execute(db.trucks.insert().values(truck=HOSTILE, created_unix_s=time.time()))
    s.start()
    yield s
    s.stop()


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/chromium-setup)")
def test_console_finds_the_drifting_truck(console_server, tmp_path):
    s = console_server
    token = s.token("engineer")
    requests, problems = [], []

    def watch(page):
        # the refused truck token's 403 is the one expected network error
        page.on("console", lambda m: m.type in ("error", "warning") and "403" not in m.text
                and problems.append(f"{m.type}: {m.text}"))
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))

    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        context.on("request", lambda r: requests.append(r.url))
        context.on("page", watch)
        page = context.new_page()
        page.goto(s.url + "/")
        playwright.expect(page.locator("#token")).to_be_focused()  # the page opens on the token field
        page.keyboard.type(s.token("truck", "DRIFT-1"))  # a truck's token is refused with a sentence
        page.keyboard.press("Enter")
        playwright.expect(page.locator("#status")).to_contain_text("engineer or admin token")
        assert page.locator("#signin").is_visible() and page.evaluate("sessionStorage.length") == 0
        assert page.evaluate(CONTRAST, "#status") >= 4.5  # WCAG AA for the error
        playwright.expect(page.locator("#token")).to_be_focused()  # back on the field, to try again
        page.keyboard.press("Tab")  # next in the focus order: the sign-in button, with a visible focus ring
        playwright.expect(page.locator("#signin-form button[type=submit]")).to_be_focused()
        ring = page.evaluate("() => { const s = getComputedStyle(document.activeElement); "
                             "return [s.outlineStyle, parseFloat(s.outlineWidth)]; }")
        assert ring[0] != "none" and ring[1] >= 2, ring
        page.keyboard.press("Shift+Tab")
        page.keyboard.type(token)
        page.keyboard.press("Enter")
        rows = page.locator("#fleet-rows .row")
        rows.nth(10).wait_for()
        assert rows.count() == 11

        # sorted by |drift| by default: the drifting truck is first and flagged
        first = rows.first
        assert first.get_attribute("data-truck") == "DRIFT-1" and "alert" in first.get_attribute("class")
        drift_text = first.locator("[role=cell]").nth(8).text_content()
        assert drift_text.startswith("+7.") or drift_text.startswith("+6.")  # 8 % of the fuel above idle
        assert page.locator("#alerts li").count() == 1 and "DRIFT-1" in page.locator("#alerts").text_content()
        # the engine's map: in the model, never missing, never an alert (its latest diagnosis named it first)
        mapped = page.locator("#fleet-rows .row[data-truck='MAP-1']")
        assert mapped.locator("[role=cell]").nth(6).text_content() == "in the model: engine_map"
        assert "alert" not in mapped.get_attribute("class") and mapped.locator(".badge").count() == 0
        page.click("#sort-drift")  # ascending, then back
        assert rows.first.get_attribute("data-truck") != "DRIFT-1"
        page.click("#sort-drift")
        assert rows.first.get_attribute("data-truck") == "DRIFT-1"

        # the hostile name is text, never markup
        assert page.locator("#fleet img").count() == 0
        assert page.locator("#fleet-rows .row", has_text=HOSTILE).count() == 1
        page.screenshot(path=tmp_path / "fleet.png", full_page=True)

        # the token: session storage only, never in the URL, no cookies, nothing in local storage
        assert page.evaluate("sessionStorage.getItem('fuelid.token')") == token
        assert page.evaluate("localStorage.length") == 0 and context.cookies() == []

        # truck view, its report, a refit with the job followed to its end
        first.locator("a.truck").click()
        versions = page.locator("#versions tbody tr")
        versions.nth(2).wait_for()
        assert page.locator("#truck-name").text_content() == "DRIFT-1"
        with context.expect_page() as popup_info:
            versions.first.locator("button", has_text="report").click()
        report = popup_info.value
        report.wait_for_load_state()
        assert report.locator("#t").text_content() == "DRIFT-1 fuel model report"  # its inline script ran
        page.click("#refit")
        # (a wait_for_function predicate would be eval'd, which the page's CSP rightly refuses)
        playwright.expect(page.locator("#job")).to_contain_text("done", timeout=20000)
        playwright.expect(versions).to_have_count(4, timeout=10000)  # the page reloads the history after the job
        page.screenshot(path=tmp_path / "truck.png", full_page=True)
        browser.close()

    assert problems == []
    assert requests and all(u.startswith(s.url + "/") for u in requests), [u for u in requests if not u.startswith(s.url)]
    assert not any(token in u for u in requests)
    assert not_blank(tmp_path / "fleet.png") and not_blank(tmp_path / "truck.png")
