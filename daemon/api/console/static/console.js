// tandemscan operator console: sign-in, cell, jobs, live progress, results (docs/console.md).
// Talks only to the daemon that served it; the API token lives in sessionStorage (this tab only).
"use strict";

const TOKEN_KEY = "tandemscan.token";
const COMPLETED = ["succeeded", "succeeded_with_gaps"];  // outputs written (with gaps: scans left out, see error)
const FINAL = [...COMPLETED, "failed", "cancelled"];
const ACTIVE = ["running", "paused", "paused_safety", "paused_fault"];
const $ = (id) => document.getElementById(id);

const state = {
  watchedId: null,      // the job the job card follows (the active one, else the last submitted)
  watched: null,        // its last body from GET /v1/jobs/{id}
  plans: {},            // job id -> PlanView of GET /v1/jobs/{id}/plan
  devices: null,        // last GET /v1/devices
  lastEventId: null,    // id of the last server-sent event seen: the resume point after a dropped stream
  streamAbort: null,
  timers: [],
  resultId: null,
};

// ------------------------------------------------------------------ API calls

class ApiError extends Error {
  constructor(status, title, detail) {
    super(detail ? `${title}: ${detail}` : title);
    this.status = status;
  }
}

function authHeaders(extra = {}) {
  const token = sessionStorage.getItem(TOKEN_KEY);
  return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
}

async function problemOf(response) {
  // RFC 9457 problem document -> ApiError with a readable message
  let title = `${response.status} ${response.statusText}`, detail = "";
  try {
    const body = await response.json();
    title = body.title || title;
    detail = body.detail || "";
  } catch (e) { /* not JSON: keep the status line */ }
  return new ApiError(response.status, title, detail);
}

async function api(method, path, body) {
  const init = { method, headers: authHeaders(body === undefined ? {} : { "Content-Type": "application/json" }) };
  if (body !== undefined) init.body = JSON.stringify(body);
  let response;
  try {
    response = await fetch(path, init);
  } catch (e) {
    throw new ApiError(0, "The daemon cannot be reached", String(e));
  }
  if (response.status === 401) {
    signOut("The token was not accepted (401): sign in again.");
    throw new ApiError(401, "Not signed in");
  }
  if (!response.ok) throw await problemOf(response);
  return path.endsWith("/view") ? response.arrayBuffer() : response.json();
}

function showMessage(text) {
  $("message-text").textContent = text;
  $("message").hidden = false;
}

async function act(fn) {
  // run a button's call; a refusal of the API shows as a readable message
  try {
    await fn();
  } catch (e) {
    if (e.status !== 401) showMessage(e.message);
  }
}

// ------------------------------------------------------------------ sign-in

async function trySession() {
  const response = await fetch("/v1/session", { headers: authHeaders() });
  if (response.ok) return response.json();
  if (response.status === 401) return null;
  throw await problemOf(response);
}

async function signIn(event) {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("token-input").value.trim());
  try {
    const session = await trySession();
    if (session === null) {
      sessionStorage.removeItem(TOKEN_KEY);
      $("signin-error").textContent = "This token is not accepted by the daemon.";
      return;
    }
    $("token-input").value = "";
    startConsole(session);
  } catch (e) {
    $("signin-error").textContent = e.message;
  }
}

function signOut(reason) {
  sessionStorage.removeItem(TOKEN_KEY);
  stopConsole();
  $("app").hidden = true;
  $("signin").hidden = false;
  $("signin-error").textContent = reason || "";
  $("token-input").focus();
}

// ------------------------------------------------------------------ the cell

function deviceDetail(d) {
  const parts = [];
  for (const [k, v] of Object.entries(d.detail || {})) {
    parts.push(`${k} ${typeof v === "number" ? (Number.isInteger(v) ? v : v.toFixed(k.endsWith("_rad") ? 3 : 1)) : v}`);
  }
  if (d.last_error) parts.push(`error: ${d.last_error}`);
  if (d.reconnects) parts.push(`reconnects ${d.reconnects}`);
  return parts.join(", ");
}

function renderDevices(snap) {
  state.devices = snap;
  const body = $("devices").tBodies[0];
  body.replaceChildren(...snap.devices.map((d) => {
    const tr = document.createElement("tr");
    tr.dataset.device = d.name;
    tr.className = d.connected ? "" : "device-fault";
    const link = d.connected ? "connected" : "disconnected";
    tr.innerHTML = `<th scope="row"></th><td class="${d.connected ? "link-up" : "link-down"}">${link}</td>` +
      `<td class="state-cell"></td><td class="detail"></td>`;
    tr.children[0].textContent = d.name;
    tr.children[2].textContent = d.state;
    tr.children[3].textContent = deviceDetail(d);
    return tr;
  }));
  $("moving").textContent = snap.moving.length ? snap.moving.map((r) => `${r} robot`).join(", ") : "none";
  renderLatch(snap.safety.latched, snap.safety.reason);
  if (state.watchedId && state.plans[state.watchedId]) drawWatchedPlan();
}

function renderLatch(latched, reason) {
  $("latch-banner").hidden = !latched;
  $("latch-reason").textContent = reason || "";
  document.body.classList.toggle("latched", latched);
}

function renderSafety(s) {
  renderLatch(s.latched, s.reason);
  const inputs = s.inputs_readable
    ? `e-stop ${s.estop ? "PRESSED" : "released"}, light curtain ${s.light_curtain_broken ? "BROKEN" : "clear"}`
    : "safety inputs unreadable";
  $("safety-inputs").textContent = `Safety inputs: ${inputs}`;
  $("reset-button").disabled = !(s.latched && s.reset_allowed);
  $("latch-hint").textContent = s.latched
    ? (s.reset_allowed ? "The inputs are clear: press Reset, then Resume the job." : "Clear the e-stop and light curtain before a reset.")
    : "";
}

function renderCalibration(cal) {
  const mounts = cal.source === "calibration" ? `calibration ${cal.file}` : cal.source;
  const v = cal.verification;
  const verified = v ? `last verification ${v.result}, ${v.age_h.toFixed(1)} h ago` : "no verification on record";
  $("calibration").textContent = `mounts: ${mounts}${cal.error ? " (" + cal.error + ")" : ""}; ${verified}`;
  $("calibration").className = v && v.result !== "pass" ? "verdict fail" : "muted";
}

async function refreshCell() {
  const [devices, safety, cal] = await Promise.all(
    [api("GET", "/v1/devices"), api("GET", "/v1/safety"), api("GET", "/v1/calibration")]);
  renderDevices(devices);
  renderSafety(safety);
  renderCalibration(cal);
}

// ------------------------------------------------------------------ jobs

function cell(text) {
  const td = document.createElement("td");
  td.textContent = text == null ? "" : String(text);
  return td;
}

function openButton(job, text) {
  const b = document.createElement("button");
  b.type = "button";
  b.textContent = text;
  b.dataset.job = job.id;
  return b;
}

function jobRow(job, withFinished) {
  const tr = document.createElement("tr");
  tr.dataset.job = job.id;
  tr.append(cell(job.id), cell(job.plan), cell(job.label), cell(job.state));
  if (withFinished) tr.append(cell(job.finished ? new Date(job.finished).toLocaleString() : ""));
  const action = document.createElement("td");
  if (FINAL.includes(job.state)) {
    const b = openButton(job, `Open result of ${job.id}`);
    b.addEventListener("click", () => act(() => openResult(job.id)));
    action.append(b);
  } else {
    const b = openButton(job, `Follow ${job.id}`);
    b.addEventListener("click", () => act(() => watch(job.id)));
    action.append(b);
  }
  tr.append(action);
  return tr;
}

async function refreshJobs() {
  const [open, done] = await Promise.all([
    api("GET", "/v1/jobs?state=queued&state=running&state=paused&state=paused_safety&state=paused_fault&limit=50"),
    api("GET", "/v1/jobs?state=succeeded&state=succeeded_with_gaps&state=failed&state=cancelled&limit=20"),
  ]);
  $("queue").tBodies[0].replaceChildren(...open.items.map((j) => jobRow(j, false)));
  $("history").tBodies[0].replaceChildren(...done.items.map((j) => jobRow(j, true)));
  const active = open.items.find((j) => ACTIVE.includes(j.state));
  if (active && active.id !== state.watchedId) await watch(active.id);
}

async function refreshPlans() {
  const plans = await api("GET", "/v1/plans");
  const select = $("plan-select");
  select.replaceChildren(...plans.filter((p) => p.valid).map((p) => {
    const o = document.createElement("option");
    o.value = p.name;
    o.textContent = `${p.name} (${p.scans} scans, ${p.transfers} transfers)${p.default ? " - default" : ""}`;
    o.selected = !!p.default;
    return o;
  }));
}

async function submitJob(event) {
  event.preventDefault();
  const body = { plan: $("plan-select").value };
  const label = $("label-input").value.trim();
  if (label) body.label = label;
  const partNumber = $("part-input").value.trim();
  if (partNumber) body.part_number = partNumber;
  const serial = $("serial-input").value.trim();
  if (serial) body.serial_number = serial;
  await act(async () => {
    const job = await api("POST", "/v1/jobs", body);
    $("label-input").value = "";
    await watch(job.id);
    await refreshJobs();
  });
}

async function watch(jobId) {
  state.watchedId = jobId;
  if (!state.plans[jobId]) state.plans[jobId] = await api("GET", `/v1/jobs/${jobId}/plan`);
  renderJob(await api("GET", `/v1/jobs/${jobId}`));
}

function renderFigures(dl, figures) {
  dl.replaceChildren();
  for (const [k, v] of Object.entries(figures || {})) {
    if (v !== null && typeof v === "object") continue;
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = k;
    dd.textContent = typeof v === "number" && !Number.isInteger(v) ? v.toFixed(4) : String(v);
    dl.append(dt, dd);
  }
}

function stepText(job) {
  const plan = state.plans[job.id];
  if (job.current_step == null) return FINAL.includes(job.state) ? "done" : "-";
  const label = plan ? plan.step_labels[job.current_step] : "";
  return `${job.current_step + 1} of ${job.steps_total}${label ? ": " + label : ""}`;
}

function renderProgress(percent) {
  $("job-progress").value = percent;
  $("job-progress-text").textContent = `${Math.round(percent)} %`;
}

function renderJob(job) {
  if (job.id !== state.watchedId) return;
  state.watched = job;
  $("watched-job").hidden = false;
  $("job-id").textContent = job.id;
  $("job-state").textContent = job.state;
  $("job-state").className = `state ${job.state}`;
  $("job-plan").textContent = `plan ${job.plan}`;
  $("job-label").textContent = job.label ? `- ${job.label}` : "";
  renderProgress(job.progress);
  $("job-step").textContent = stepText(job);
  $("job-error").textContent = job.error || "";
  renderFigures($("job-figures"), job.figures);
  $("pause-button").disabled = job.state !== "running";
  $("resume-button").disabled = !["paused", "paused_safety", "paused_fault"].includes(job.state);
  $("cancel-button").disabled = FINAL.includes(job.state);
  $("open-result-button").hidden = !FINAL.includes(job.state);
  drawWatchedPlan();
}

function drawWatchedPlan() {
  const job = state.watched, plan = job && state.plans[job.id];
  if (plan) drawPlan($("plan-svg"), plan, job.current_step, state.devices);
}

async function jobAction(verb) {
  await act(async () => {
    renderJob(await api("POST", `/v1/jobs/${state.watchedId}/${verb}`));
    await refreshCell();
  });
}

// ------------------------------------------------------------------ a finished job

function verdictOf(job, report) {
  if (!COMPLETED.includes(job.state)) return { kind: "fail", text: `Job ${job.state}${job.error ? ": " + job.error : ""}` };
  if (job.state === "succeeded_with_gaps") return { kind: "fail", text: `Succeeded with gaps: ${job.error}` };
  const ins = report && report.inspection;
  const tol = ins && ins.as_measured && ins.as_measured.tolerance;
  if (!ins || !ins.verdict || !tol) {
    const why = ins && (ins.skipped || ins.failed);
    return { kind: "pass", text: `Succeeded; no inspection${why ? ": " + why : ""}` };
  }
  const band = `[${tol.lower_mm.toFixed(3)}, ${tol.upper_mm.toFixed(3)}] mm`;
  const areas = ins.deviations || [];
  const how = ins.alignment ? `, aligned by ${ins.alignment.method}` : "";
  const share = `${tol.in_pct.toFixed(1)} % of the points within ${band}${how}`;
  const rule = ins.decision_rule_label ? ` (${ins.decision_rule_label})` : "";
  const u = ins.uncertainty ? `; U ${ins.uncertainty.median_mm.toFixed(3)} mm (k = ${ins.uncertainty.k})` : "";
  const inst = ins.installation ? `; mounts: ${ins.installation.source}` : "";
  if (ins.verdict === "pass") {
    return { kind: "pass", text: `Inspection pass${rule}: no deviation area beyond ${band}; ${share}${u}${inst}` };
  }
  if (ins.verdict === "indeterminate") {
    const why = (ins.verdict_reasons || [])[0];
    return { kind: "indeterminate", text: `Inspection indeterminate${rule}: ${why || "not proven either way"}${u}${inst}` };
  }
  const worst = areas.length ? ` (largest: ${areas[0].side} ${areas[0].extreme_mm.toFixed(3)} mm, ` +
    `${areas[0].area_mm2.toFixed(0)} mm^2)` : "";
  return {
    kind: "fail",
    text: `Inspection fail${rule}: ${areas.length} deviation area${areas.length === 1 ? "" : "s"} beyond ${band}${worst}; ${share}${u}${inst}`,
  };
}

async function openResult(jobId) {
  const job = await api("GET", `/v1/jobs/${jobId}`);
  state.resultId = jobId;
  $("result-panel").hidden = false;
  $("result-id").textContent = jobId;
  const base = `/v1/jobs/${jobId}`;
  $("link-report").href = `${base}/files/report.html`;
  $("link-e57").href = `${base}/files/cloud.e57`;
  $("link-cloud").href = `${base}/cloud`;
  let report = null;
  if (COMPLETED.includes(job.state)) report = await api("GET", `${base}/report`);
  const verdict = verdictOf(job, report);
  $("verdict").textContent = verdict.text;
  $("verdict").className = `verdict ${verdict.kind}`;
  renderFigures($("result-figures"), job.figures);
  await showTrends(report);
  $("result-panel").scrollIntoView({ block: "start" });
  $("view-status").textContent = "loading the cloud...";
  if (!COMPLETED.includes(job.state)) {
    $("view-status").textContent = "no cloud: the job did not finish";
    return;
  }
  const buffer = await api("GET", `${base}/view`);
  const info = cloudView.show(buffer);
  renderColourBar(info);
  $("view-status").textContent = `${info.points.toLocaleString()} of ${info.points_total.toLocaleString()} points` +
    ` (frame ${info.frame}); drag to turn, wheel or pinch to zoom`;
  $("cloud-canvas").dataset.points = String(info.points);
}

// ------------------------------------------------------------------ a characteristic over serials

async function showTrends(report) {
  const ins = report && report.inspection;
  const part = ins && ins.part && ins.part.part_number;
  const chars = (ins && ins.characteristics) || [];
  $("trend-box").hidden = !part || !chars.length;
  if ($("trend-box").hidden) return;
  const select = $("trend-select");
  select.replaceChildren(...chars.map((c) => new Option(`${c.id} ${c.name} (${c.status})`, c.id)));
  const failing = chars.find((c) => c.status === "fail");
  select.value = (failing || chars[0]).id;
  select.onchange = () => act(() => drawTrend(part, select.value));
  await drawTrend(part, select.value);
}

async function drawTrend(part, id) {
  const t = await api("GET", `/v1/parts/${encodeURIComponent(part)}/characteristics/${encodeURIComponent(id)}/trend`);
  const svg = $("trend-svg");
  const w = Number(svg.getAttribute("width")), h = Number(svg.getAttribute("height")), pad = 28;
  const pts = t.points.filter((p) => p.actual_mm !== null);
  const ys = [...pts.map((p) => p.actual_mm), t.lower_mm, t.upper_mm, t.ucl_mm ?? 0, t.lcl_mm ?? 0];
  const lo = Math.min(...ys), hi = Math.max(...ys), span = hi - lo || 1;
  const x = (i) => pad + (i * (w - 2 * pad)) / Math.max(pts.length - 1, 1);
  const y = (v) => h - pad - ((v - lo) / span) * (h - 2 * pad);
  const line = (v, colour, dash) => svgElement("line", { x1: pad, x2: w - pad, y1: y(v), y2: y(v), stroke: colour,
    "stroke-dasharray": dash, "stroke-width": 1 });
  svg.replaceChildren(line(t.lower_mm, "#2fbf4a", ""), line(t.upper_mm, "#2fbf4a", ""));
  if (t.mean_mm !== null) svg.append(line(t.mean_mm, "#444", ""), line(t.ucl_mm, "#d7261e", "4 3"),
    line(t.lcl_mm, "#d7261e", "4 3"));
  svg.append(svgElement("polyline", { points: pts.map((p, i) => `${x(i)},${y(p.actual_mm)}`).join(" "),
    fill: "none", stroke: "#1d3fbf", "stroke-width": 1.5 }));
  pts.forEach((p, i) => {
    const dot = svgElement("circle", { cx: x(i), cy: y(p.actual_mm), r: 3, class: "trend-point",
      fill: p.status === "fail" ? "#d7261e" : "#1d3fbf" });
    dot.append(svgElement("title", {}, `${p.serial ?? p.job}: ${p.actual_mm.toFixed(3)} mm, ${p.status}`));
    svg.append(dot);
  });
  svg.dataset.points = String(pts.length);
  const f = (v, d = 3) => (v === null ? "-" : v.toFixed(d));
  $("trend-text").textContent = `${pts.length} serials, mean ${f(t.mean_mm)} mm, std ${f(t.std_mm)} mm, ` +
    `limits ${f(t.lcl_mm)}..${f(t.ucl_mm)} mm, Cp ${f(t.cp, 2)}, Cpk ${f(t.cpk, 2)}` + (t.drift ? `; ${t.drift}` : "");
}

function renderColourBar(info) {
  $("colour-bar").hidden = !info.deviation;
  if (!info.deviation) return;
  const [lo, hi] = info.colour_scale_mm, [lower, upper] = info.tolerance_mm || [0, 0];
  const at = (v) => `${(100 * (v - lo)) / (hi - lo)}%`;
  $("colour-gradient").style.background = `linear-gradient(to right, ${info.colours.join(", ")})`;
  $("tolerance-band").style.left = at(lower);
  $("tolerance-band").style.width = `calc(${at(upper)} - ${at(lower)})`;
  $("colour-ticks").replaceChildren(...[lo, lower, 0, upper, hi].map((v) => {
    const s = document.createElement("span");
    s.style.left = at(v);
    s.textContent = `${v > 0 ? "+" : ""}${v.toFixed(2)}`;
    return s;
  }));
}

// ------------------------------------------------------------------ the event stream

function onEvent(kind, data) {
  if (kind === "progress" && data.job_id === state.watchedId && state.watched) {
    renderJob({ ...state.watched, progress: data.progress, current_step: data.current_step,
      figures: data.figures || state.watched.figures });
  } else if (kind === "state") {
    if (data.job_id === state.watchedId) act(() => watch(data.job_id));
    act(refreshJobs);
  } else if (kind === "device" || kind === "safety") {
    act(refreshCell);
  }
}

async function readStream(signal) {
  const headers = authHeaders(state.lastEventId ? { "Last-Event-ID": state.lastEventId } : {});
  const response = await fetch("/v1/events", { headers, signal });
  if (response.status === 401) {
    signOut("The token was not accepted (401): sign in again.");
    return;
  }
  if (!response.ok) throw await problemOf(response);
  $("stream-status").textContent = "event stream: live";
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let cut;
    while ((cut = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, cut);
      buffer = buffer.slice(cut + 2);
      let id = null, kind = "message", data = null;
      for (const line of block.split("\n")) {
        if (line.startsWith("id: ")) id = line.slice(4);
        else if (line.startsWith("event: ")) kind = line.slice(7);
        else if (line.startsWith("data: ")) data = JSON.parse(line.slice(6));
      }
      if (id !== null) state.lastEventId = id;
      if (data !== null) onEvent(kind, data);
    }
  }
}

async function followEvents() {
  // reconnects after a dropped stream, replaying what was missed from Last-Event-ID
  const controller = new AbortController();
  state.streamAbort = controller;
  while (!controller.signal.aborted) {
    try {
      await readStream(controller.signal);
    } catch (e) {
      if (controller.signal.aborted) return;
    }
    if (controller.signal.aborted) return;
    $("stream-status").textContent = `event stream: reconnecting (after event ${state.lastEventId || "-"})`;
    await new Promise((r) => setTimeout(r, 1000));
  }
}

// ------------------------------------------------------------------ start and stop

function startConsole(session) {
  $("signin").hidden = true;
  $("app").hidden = false;
  $("version").textContent = `daemon ${session.version}${session.token_required ? "" : " (no token required)"}`;
  act(async () => {
    await Promise.all([refreshCell(), refreshPlans(), refreshJobs()]);
  });
  followEvents();
  state.timers.push(setInterval(() => act(refreshCell), 1000));   // which robot moves has no event
  state.timers.push(setInterval(() => act(refreshJobs), 10000));
}

function stopConsole() {
  if (state.streamAbort) state.streamAbort.abort();
  state.timers.forEach(clearInterval);
  state.timers = [];
}

function wire() {
  $("signin-form").addEventListener("submit", signIn);
  $("signout-button").addEventListener("click", () => signOut("Signed out."));
  $("message-close").addEventListener("click", () => { $("message").hidden = true; });
  $("stop-button").addEventListener("click", () => act(async () => {
    renderDevices(await api("POST", "/v1/safety/stop"));
    await refreshCell();
  }));
  $("reset-button").addEventListener("click", () => act(async () => {
    renderDevices(await api("POST", "/v1/safety/reset"));
    await refreshCell();
  }));
  $("submit-form").addEventListener("submit", submitJob);
  $("pause-button").addEventListener("click", () => jobAction("pause"));
  $("resume-button").addEventListener("click", () => jobAction("resume"));
  $("cancel-button").addEventListener("click", () => jobAction("cancel"));
  $("open-result-button").addEventListener("click", () => act(() => openResult(state.watchedId)));
  cloudView.attach($("cloud-canvas"), {
    reset: $("view-reset"), zoomIn: $("view-zoom-in"), zoomOut: $("view-zoom-out"), pointSize: $("point-size"),
  });
}

window.addEventListener("DOMContentLoaded", async () => {
  wire();
  try {
    const session = await trySession();
    if (session) startConsole(session);
    else signOut("");
  } catch (e) {
    signOut(e.message);
  }
});
