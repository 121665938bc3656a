// The fleet engineer's console. Every value from the server goes into the page through textContent (truck
// names are VINs read off the bus: untrusted); the token lives in sessionStorage and in Authorization headers
// only, never in a URL.
"use strict";

const TOKEN_KEY = "fuelid.token";
const state = { fleet: null, sortKey: "drift_percent", sortAsc: false, truck: null, points: "", threshold: "" };
const $ = (id) => document.getElementById(id);

function el(tag, text, className) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  if (className) node.className = className;
  return node;
}

function num(x, digits) {
  return x === null || x === undefined ? "–" : Number(x).toFixed(digits);
}

function signed(x, digits) {
  return x === null || x === undefined ? "–" : (x > 0 ? "+" : "") + Number(x).toFixed(digits);
}

function plusMinus(value, std, digits, sign) {
  if (value === null || value === undefined) return "–";
  const v = sign ? signed(value, digits) : num(value, digits);
  return std === null || std === undefined ? v : `${v} ± ${num(std, digits)}`;
}

function when(unixS) {
  return unixS ? new Date(unixS * 1000).toISOString().replace("T", " ").slice(0, 16) : "–";
}

function whenNs(ns) {
  return ns === null || ns === undefined ? "–" : when(ns / 1e9);
}

function status(message, isError) {
  const s = $("status");
  s.textContent = message || "";
  s.className = isError ? "error" : "";
}

async function api(method, path) {
  const token = sessionStorage.getItem(TOKEN_KEY);
  const response = await fetch(path, { method, headers: { Authorization: `Bearer ${token}` }, cache: "no-store" });
  let body = null;
  try { body = await response.json(); } catch (e) { body = null; }
  if (response.status === 401 || response.status === 403) {  // unknown, revoked, or a truck's token
    signOut(response.status === 401 ? "the token was refused (missing, unknown or revoked)"
      : "this token may not read the fleet: sign in with an engineer or admin token");
    throw new Error("signed out");
  }
  if (!response.ok) throw new Error((body && body.detail) || `${method} ${path}: HTTP ${response.status}`);
  return body;
}

function query() {
  const q = new URLSearchParams();
  if (state.points) q.set("points", state.points);
  if (state.threshold) q.set("threshold", state.threshold);
  const s = q.toString();
  return s ? `?${s}` : "";
}

// --- fleet view ---

function sortValue(t) {
  const v = t[state.sortKey];
  return state.sortKey === "drift_percent" && v !== null ? Math.abs(v) : v;  // the worst drift either way
}

function compare([x, a], [y, b]) {
  if (x === y) return a.truck < b.truck ? -1 : 1;
  if (x === null || x === undefined) return 1;  // unknowns last in both directions
  if (y === null || y === undefined) return -1;
  const order = typeof x === "string" ? x.localeCompare(y) : x - y;
  return state.sortAsc ? order : -order;
}

// "in the model: a, b; missing: c": effects the model carries and hidden effects its diagnosis recommends
function effectsText(t) {
  const parts = [];
  if (t.effects.length) parts.push(`in the model: ${t.effects.join(", ")}`);
  if (t.missing_effects.length) parts.push(`missing: ${t.missing_effects.join(", ")}`);
  return parts.join("; ") || "–";
}

function cell(text, className) {
  const c = el("span", text, className);
  c.setAttribute("role", "cell");
  return c;
}

function renderFleet() {
  const fleet = state.fleet;
  const body = $("fleet-rows");
  body.replaceChildren();
  const rows = fleet.trucks.map((t) => [sortValue(t), t]).sort(compare).map(([, t]) => t);
  const fragment = document.createDocumentFragment();
  for (const t of rows) {
    const tr = el("div", null, t.alerts.length ? "row alert" : "row");  // a grid row: off-screen rows are
    tr.setAttribute("role", "row");                                      // neither laid out nor painted
    tr.dataset.truck = t.truck;
    const name = cell();
    const link = el("a", t.truck, "truck");  // opened by the table's click handler; a plain link lays out cheaper
    link.href = "#";                        // than a button, which matters at 1,000 rows
    name.append(link);
    tr.append(name, cell(num(t.data_hours, 1)), cell(when(t.last_upload_unix_s)),
      cell(t.latest_version ?? "–"), cell(num(t.fit_percent, 1)), cell(num(t.cycle_fuel_error_percent, 2)),
      cell(effectsText(t), "text"),
      cell(t.steady_fuel === null ? "–" : `${plusMinus(t.steady_fuel, t.steady_fuel_std, 2)} ${t.unit || ""}`),
      cell(plusMinus(t.drift_percent, t.drift_std_percent, 1, true)), cell(signed(t.vs_fleet_percent, 1)));
    const alerts = cell(null, "text");
    for (const a of t.alerts) alerts.append(el("span", a.kind, "badge"));
    if (t.note && t.steady_fuel === null) alerts.append(el("span", t.note, "hint"));
    tr.append(alerts);
    fragment.append(tr);
  }
  body.append(fragment);
  for (const b of document.querySelectorAll("#fleet .head button")) {
    b.classList.toggle("sorted", b.dataset.key === state.sortKey);
    b.classList.toggle("asc", b.dataset.key === state.sortKey && state.sortAsc);
  }
  const list = $("alerts");
  list.replaceChildren();
  const all = fleet.trucks.flatMap((t) => t.alerts);
  for (const a of all) {
    const li = el("li");
    const link = el("button", a.truck, "link");
    link.type = "button";
    link.addEventListener("click", () => openTruck(a.truck));
    li.append(link, document.createTextNode(` (version ${a.version}): ${a.message}`));
    list.append(li);
  }
  $("alert-count").textContent = `(${all.length})`;
  $("fleet-median").textContent = fleet.fleet_median_steady_fuel === null ? "" :
    `fleet median steady fuel ${num(fleet.fleet_median_steady_fuel, 2)} at ${fleet.points.join(", ")}; threshold ${fleet.threshold_percent} %`;
}

async function loadFleet() {
  status("loading the fleet…");
  const t0 = performance.now();
  state.fleet = await api("GET", `/api/v1/fleet${query()}`);
  $("points").value = state.fleet.points.join(",");
  $("threshold").value = state.fleet.threshold_percent;
  renderFleet();
  status(`${state.fleet.trucks.length} trucks, shown in ${Math.round(performance.now() - t0)} ms`);
  document.body.dataset.fleetRendered = String(performance.now() - t0);
}

// --- truck view ---

async function openReport(truck, version) {
  try {
    const link = await api("POST", `/api/v1/trucks/${encodeURIComponent(truck)}/models/${version}/report-link`);
    window.open(link.url, "_blank", "noopener");
  } catch (e) { status(e.message, true); }
}

function renderTruck(h) {
  $("truck-name").textContent = h.truck;
  const versions = $("versions").tBodies[0];
  versions.replaceChildren();
  for (const v of h.versions.slice().reverse()) {
    const tr = el("tr", null, v.drift_alert ? "alert" : "");
    const report = el("td");
    if (v.has_report) {
      const b = el("button", "report", "link");
      b.type = "button";
      b.addEventListener("click", () => openReport(h.truck, v.version));
      report.append(b);
    }
    tr.append(el("td", v.version), el("td", when(v.created_unix_s)), el("td", num(v.fit_percent, 1)),
      el("td", v.rmse === null ? "–" : `${num(v.rmse, 3)} ${v.unit || ""}`), el("td", num(v.cycle_fuel_error_percent, 2)),
      el("td", plusMinus(v.steady_fuel, v.steady_fuel_std, 2)),
      el("td", v.version === h.versions[0].version ? "reference" : plusMinus(v.drift_percent, v.drift_std_percent, 1, true)),
      el("td", v.effects.join(", ") || "–", "text"), el("td", v.missing_effects.join(", ") || "–", "text"), report);
    if (v.note && v.steady_fuel === null) tr.cells[5].textContent = v.note;
    versions.append(tr);
  }
  const files = $("files").tBodies[0];
  files.replaceChildren();
  for (const f of h.files) {
    const hours = f.start_ns === null ? null : (f.end_ns - f.start_ns) / 3.6e12;
    files.append(row([whenNs(f.start_ns), whenNs(f.end_ns), num(hours, 2), f.messages, num(f.size_bytes / 1e6, 2),
      f.sha256.slice(0, 12)]));
  }
  renderJobs(h.jobs);
}

function row(cells) {
  const tr = el("tr");
  for (const c of cells) tr.append(el("td", c));
  return tr;
}

function renderJobs(jobs) {
  const body = $("jobs").tBodies[0];
  body.replaceChildren();
  for (const j of jobs) body.append(row([j.id, j.reason, j.status, when(j.created_unix_s), j.model_version ?? "–", j.error || ""]));
}

async function openTruck(truck) {
  state.truck = truck;
  $("fleet-view").hidden = true;
  $("truck-view").hidden = false;
  $("job").textContent = "";
  status("loading the truck…");
  try {
    renderTruck(await api("GET", `/api/v1/trucks/${encodeURIComponent(truck)}/history${query()}`));
    status("");
  } catch (e) { status(e.message, true); }
}

async function refit() {
  const truck = state.truck;
  $("refit").disabled = true;
  try {
    let job = await api("POST", `/api/v1/trucks/${encodeURIComponent(truck)}/refit`);
    for (;;) {
      $("job").textContent = `job ${job.id}: ${job.status}${job.error ? " — " + job.error : ""}`;
      if (job.status !== "queued" && job.status !== "running") break;  // done, failed, or unchanged (no new data)
      await new Promise((resolve) => setTimeout(resolve, 1000));
      job = await api("GET", `/api/v1/jobs/${job.id}`);
    }
    if (state.truck === truck) renderTruck(await api("GET", `/api/v1/trucks/${encodeURIComponent(truck)}/history${query()}`));
    $("job").textContent = `job ${job.id}: ${job.status}${job.model_version ? ", version " + job.model_version : ""}${job.error ? " — " + job.error : ""}`;
  } catch (e) { status(e.message, true); }
  $("refit").disabled = false;
}

// --- sign-in ---

function signOut(message) {
  sessionStorage.removeItem(TOKEN_KEY);
  $("app").hidden = true;
  $("signout").hidden = true;
  $("signin").hidden = false;
  status(message || "", Boolean(message));
  $("token").focus();
}

async function start() {
  $("signin").hidden = true;
  $("app").hidden = false;
  $("signout").hidden = false;
  try { await loadFleet(); } catch (e) { if (e.message !== "signed out") status(e.message, true); }
}

document.addEventListener("DOMContentLoaded", () => {
  $("signin-form").addEventListener("submit", (event) => {
    event.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $("token").value.trim());
    $("token").value = "";
    start();
  });
  $("signout").addEventListener("click", () => signOut(""));
  $("settings").addEventListener("submit", (event) => {
    event.preventDefault();
    state.points = $("points").value.trim();
    state.threshold = $("threshold").value.trim();
    loadFleet().catch((e) => status(e.message, true));
  });
  for (const b of document.querySelectorAll("#fleet .head button")) {
    b.addEventListener("click", () => {
      state.sortAsc = state.sortKey === b.dataset.key ? !state.sortAsc : b.dataset.key === "truck";
      state.sortKey = b.dataset.key;
      renderFleet();
    });
  }
  $("back").addEventListener("click", () => {
    state.truck = null;
    $("truck-view").hidden = true;
    $("fleet-view").hidden = false;
    loadFleet().catch((e) => status(e.message, true));
  });
  $("refit").addEventListener("click", refit);
  $("fleet-rows").addEventListener("click", (event) => {
    const link = event.target.closest("a.truck");
    if (link) {
      event.preventDefault();
      openTruck(link.closest(".row").dataset.truck);
    }
  });
  if (sessionStorage.getItem(TOKEN_KEY)) start();
  else $("token").focus();
});
