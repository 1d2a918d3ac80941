"use strict";
// The operator panel: one snapshot, then every change over server-sent events; each section has renderers.
// window.panel.latencies holds, per change, the seconds from the server's event to the page's updated DOM.

const token = new URLSearchParams(location.search).get("token");
const state = { seq: 0, sections: {} };
window.panel = { state, latencies: [] };
const $ = (id) => document.getElementById(id);
const S = () => state.sections;
const PHASE_COLOR = { measure: "var(--measure)", verify: "var(--verify)", verify_after: "var(--after)", acceptance: "var(--after)" };
const FINAL = ["complete", "interrupted", "refused", "not started", "failed"];

function fmt(v, digits = 3) {
  return v === null || v === undefined ? "-" : Number(v).toFixed(digits);
}
function dur(s) {
  if (s === null || s === undefined || !isFinite(s)) return "-";
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return h ? `${h} h ${m} min` : m ? `${m} min ${sec} s` : `${sec} s`;
}
function esc(text) {
  return String(text ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}
function q(path) {
  return path + (token ? (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : "");
}

async function post(path, body = {}) {
  const headers = { "Content-Type": "application/json", "X-Hilcal-Panel": "1" };
  if (token) headers["X-Hilcal-Token"] = token;
  const r = await fetch(path, { method: "POST", headers, body: JSON.stringify(body) });
  const data = await r.json().catch(() => ({ error: r.statusText }));
  if (!r.ok) throw new Error(data.error || r.statusText);
  return data;
}

// ---------------------------------------------------------------- live state

const RENDER = {
  run: [renderRun, renderControls, renderResult],
  plan: [renderPlan],
  progress: [renderProgress, renderPlan],
  controller: [renderStation],
  cmm: [renderStation],
  measurements: [renderErrors, renderVerification, renderPlan],
  prompt: [renderQuestion, renderControls],
  identification: [renderIdentification],
  upload: [renderUpload],
  result: [renderResult, renderControls],
  diagnosis: [renderDiagnosis],
  adaptive: [renderAdaptive],
  timeline: [renderTimeline],
};

function renderAll() {
  for (const fn of new Set(Object.values(RENDER).flat())) fn();
}

// Changes are applied at once and drawn once per animation frame (a burst of moves redraws once); each
// change's delay is taken when the frame that shows it has updated the DOM.
const dirty = new Set();
let pendingTimes = [];
let frameRequested = false;

function apply(ev) {
  if (ev.seq <= state.seq) return;
  if (ev.op === "set") S()[ev.section] = ev.value;
  else (S()[ev.section] = S()[ev.section] || []).push(ev.value);
  state.seq = ev.seq;
  for (const fn of RENDER[ev.section] || []) dirty.add(fn);
  if (pendingTimes.length < 10000) pendingTimes.push([ev.section, ev.t]);  // a hidden tab draws nothing
  if (!frameRequested) {
    frameRequested = true;
    requestAnimationFrame(draw);
  }
}

function draw() {
  frameRequested = false;
  for (const fn of dirty) fn();
  dirty.clear();
  document.body.dataset.seq = state.seq;
  const now = Date.now() / 1000;
  for (const [section, t] of pendingTimes) window.panel.latencies.push([section, now - t]);
  pendingTimes = [];
  if (window.panel.latencies.length > 50000) window.panel.latencies.splice(0, 10000);
}

function setLink(up, text) {
  $("link").className = "link " + (up ? "up" : "down");
  $("link").textContent = text;
}

function connect() {
  const es = new EventSource(q("/api/events"));
  es.addEventListener("snapshot", (e) => {
    const snap = JSON.parse(e.data);
    state.seq = snap.seq;
    state.sections = snap.sections;
    dirty.clear();
    pendingTimes = [];
    views.sha = null;
    renderAll();
    document.body.dataset.seq = state.seq;
    setLink(true, "live");
    if (S().run.mode === "history" && !connect.shown) showView("history");
    connect.shown = true;
  });
  es.onmessage = (e) => apply(JSON.parse(e.data));
  es.addEventListener("closed", () => {
    es.close();
    setLink(false, "panel closed");
  });
  es.onerror = () => setLink(false, "reconnecting");
}

// ---------------------------------------------------------------- header, controls, question

function renderRun() {
  const run = S().run || {};
  const parts = [run.run_id, run.robot, run.operator && `operator ${run.operator}`, run.resumed && "resumed"];
  $("run-title").textContent = parts.filter(Boolean).join(" · ") || (run.mode === "history" ? "history" : "no run");
  const status = run.status || "idle";
  $("status").textContent = status;
  $("status").className = "badge " + status.split(" ")[0];
}

function renderControls() {
  const status = (S().run || {}).status;
  const p = S().prompt;
  const pausedQuestion = p && p.open && p.kind === "pause";
  $("pause").disabled = !(status === "running") || pausedQuestion;
  $("continue").disabled = !pausedQuestion;
  $("abort").disabled = !["running", "paused", "waiting to start"].includes(status);
  $("close-panel").classList.toggle("hidden", !(S().run.mode === "run" && FINAL.includes(status)));
}

const QUESTION_TITLES = { start: "Start the run", prompt: "Operator confirmation", upload: "Approve the parameter upload",
  pause: "Paused: motion stopped" };
const QUESTION_BUTTONS = { start: ["Start", "Do not start"], prompt: ["Yes", "No"],
  upload: ["Upload to controller", "Do not upload"], pause: ["Continue", "Abort run"] };

function renderQuestion() {
  const p = S().prompt, box = $("question");
  if (!p || !p.open) {
    box.classList.add("hidden");
    box.dataset.id = "";
    return;
  }
  if (box.dataset.id === String(p.id)) return;  // keep what the operator is typing or ticking
  box.dataset.id = p.id;
  box.className = "card question " + p.kind;
  $("question-title").textContent = QUESTION_TITLES[p.kind] || "Question";
  $("question-text").textContent = p.text;
  $("question-error").textContent = "";
  const [yes, no] = QUESTION_BUTTONS[p.kind] || ["Yes", "No"];
  $("question-yes").textContent = yes;
  $("question-no").textContent = no;
  $("start-form").classList.toggle("hidden", p.kind !== "start");
  if (p.kind === "start") {
    $("operator-name").value = (p.detail && p.detail.operator) || "";
    showPlanForm((p.detail || {}).plan);
  }
  $("upload-confirm-label").classList.toggle("hidden", p.kind !== "upload");
  $("upload-confirm").checked = false;
  $("question-yes").disabled = p.kind === "upload";
  $("question-detail").innerHTML = p.kind === "upload" ? uploadDetail(p.detail || {}) : "";
}

function brief(b) {
  return b ? `max ${fmt(b.max_position_mm, 4)} mm, RMS ${fmt(b.rms_position_mm, 4)} mm; ` +
    `max ${fmt(b.max_orientation_deg, 5)}°, RMS ${fmt(b.rms_orientation_deg, 5)}°` : "-";
}

function spread(m) {
  return m ? `RMS ${fmt(m.rms_position_mm, 4)} mm, worst pose ${fmt(m.max_position_mm, 4)} mm; ` +
    `RMS ${fmt(m.rms_orientation_deg, 5)}°` : "-";
}

function physicsDetail(p) {
  if (!p) return "";
  if (p.enabled === false) {
    return `<p id="upload-physics">Physics not diagnosed (--physics off): the geometry alone is uploaded.</p>`;
  }
  const items = [...(p.corrects || []), ...(p.leaves || []), ...(p.by_hand || []).map((t) => `Set by hand: ${t}`)];
  if ((p.explained || []).length) {
    items.push(`The geometric fit alone needed ${p.explained.join("; ")}: the physics above explains it, so the ` +
      "geometry fitted together with it is the one uploaded.");
  }
  return `<div id="upload-physics"><p><b>What this run's recording shows beyond the geometry</b> (faults first):</p>
    <ul>${items.map((t) => `<li>${esc(t)}</li>`).join("")}</ul></div>`;
}

function blockSummary(b) {
  if (!b) return "none: the controller keeps its own";
  const terms = [["scale_ppm", "scale", "ppm", 1], ["backlash_mm", "backlash", "µm", 1000],
    ["compliance_mm_per_kn", "compliance", "µm/kN", 1000], ["compliance_mm_per_kn_m", "compliance per metre",
      "µm/(kN m)", 1000], ["thermal_ppm_per_k", "thermal", "ppm/K", 1]];
  const parts = terms.filter(([k]) => (b[k] || []).some((v) => v !== 0)).map(([k, label, unit, f]) =>
    `${label} ${b[k].map((v) => fmt(v * f, 1)).join(", ")} ${unit}`);
  const points = ((b.table_mm || [[]])[0] || []).length;
  if (points) parts.push(`stroke table of ${points} points per leg`);
  return parts.join("; ") || "corrects nothing";
}

function uploadDetail(d) {
  const rows = (d.diff || []).map((r) => `<tr><td>${esc(r.name)}</td><td>${fmt(r.live_mm, 4)}</td>` +
    `<td>${fmt(r.new_mm, 4)}</td><td>${(r.delta_mm >= 0 ? "+" : "") + fmt(r.delta_mm, 4)}</td></tr>`).join("");
  const offsetsOnly = d.mode === "offsets_only";
  const geometryOnly = (offsetsOnly || (d.physics && d.physics.enabled !== false)) && d.predicted_geometry_only ?
    `<tr><th>${offsetsOnly ? "With the joint positions too (this controller holds the leg offsets only)"
      : "Predicted with the geometry alone"}</th><td id="predicted-geometry-only">${brief(d.predicted_geometry_only)}
      </td></tr>` : "";
  return `${physicsDetail(d.physics)}<table class="kv" id="upload-prediction">
      <tr><th>Verification poses now (measured)</th><td>${brief(d.measured_before)}</td></tr>
      <tr><th>Predicted after the upload</th><td id="predicted-after">${brief(d.predicted_after)}</td></tr>
      ${geometryOnly}
      <tr><th>Compensation block</th><td id="upload-block">${esc(blockSummary(d.compensation_block))}</td></tr>
      <tr><th>Basis</th><td>${esc(d.predicted_basis)}</td></tr>
      <tr><th>Parameter uncertainty in the workspace</th><td id="model-uncertainty">${spread(d.model_uncertainty)}
        <span class="sub">${esc(d.model_uncertainty_basis || "no covariance for this estimator")}</span>
        ${d.model_incomplete_note ? `<br><span class="sub" id="model-incomplete">${esc(d.model_incomplete_note)}</span>`
          : ""}</td></tr>
      ${d.uncompensated ? `<tr><th>Left uncompensated</th><td>${brief(d.uncompensated)}</td></tr>` : ""}
      ${(d.out_of_reach || []).length ? `<tr><th>Out of reach after the upload</th><td id="out-of-reach">
        ${d.out_of_reach.map(esc).join("<br>")}</td></tr>` : ""}
      <tr><th>Estimator, mode</th><td>${esc(d.estimator)}, ${esc(d.mode)}</td></tr>
      <tr><th>New set SHA-256</th><td><code id="upload-sha">${esc(d.new_sha256)}</code></td></tr></table>
    <p><b id="diff-count">${(d.diff || []).length}</b> parameters change:</p>
    <div class="scroll"><table class="data" id="upload-diff"><tr><th>parameter</th><th>live mm</th><th>new mm</th>
      <th>change mm</th></tr>${rows}</table></div>`;
}

// The start form's measurement plan: a new run's can change there (adaptive, its target and the whole run's time).
function showPlanForm(plan) {
  $("plan-form").classList.toggle("hidden", !plan);
  if (!plan) return;
  $("plan-adaptive").checked = !!plan.adaptive;
  $("plan-target").value = plan.target_mm == null ? "" : plan.target_mm;
  $("plan-minutes").value = plan.max_minutes == null ? "" : plan.max_minutes;
  $("plan-minutes").placeholder = `the fixed plan's: ${fmt(plan.fixed_minutes, 1)}`;
  for (const id of ["plan-adaptive", "plan-target", "plan-minutes"]) $(id).disabled = !plan.choosable;
  $("plan-note").textContent = plan.choosable ? `The fixed plan takes about ${fmt(plan.fixed_minutes, 1)} min of ` +
    "machine time; the adaptive one stops when the accuracy is proven, and always within the time given." :
    "A resumed run goes on with the plan it started with.";
  const toggle = () => $("plan-adaptive-options").classList.toggle("hidden", !$("plan-adaptive").checked);
  $("plan-adaptive").onchange = toggle;
  toggle();
}

function chosenPlan() {
  const plan = ((S().prompt || {}).detail || {}).plan;
  if (!plan || !plan.choosable) return undefined;
  const number = (id) => ($(id).value === "" ? null : Number($(id).value));
  return { adaptive: $("plan-adaptive").checked, target_mm: number("plan-target"), max_minutes: number("plan-minutes") };
}

async function answer(yes) {
  const p = S().prompt;
  if (!p || !p.open) return;
  const body = { answer: yes };
  if (p.kind === "start") {
    body.operator = $("operator-name").value;
    if (yes) body.plan = chosenPlan();
  }
  if (p.kind === "upload" && yes) body.confirm_sha256 = p.detail.new_sha256;
  try {
    await post(`/api/questions/${p.id}`, body);
  } catch (e) {
    $("question-error").textContent = e.message;
  }
}

async function command(action) {
  $("control-error").textContent = "";
  try {
    await post(`/api/${action}`);
  } catch (e) {
    $("control-error").textContent = e.message;
  }
}

// ---------------------------------------------------------------- station and progress

function renderStation() {
  const c = S().controller || {}, cmm = S().cmm || {};
  const alive = c.alive;
  $("ctl-state").innerHTML = c.state ? `<span class="${alive ? "ok" : "bad"}">${esc(c.state)}</span>` + (c.can ? ` <span class="sub">CAN ${esc(c.can)}</span>` : "") : (alive === false ? '<span class="bad">lost</span>' : "-");
  $("ctl-heartbeat").innerHTML = c.heartbeat_age_ms == null ? "-" :
    `<span class="${alive ? "ok" : "bad"}">${fmt(c.heartbeat_age_ms, 0)} ms ago</span> <span class="sub">(lost after ${fmt(c.heartbeat_timeout_ms, 0)} ms)</span>`;
  $("ctl-estop").innerHTML = c.estop == null ? "-" : c.estop ? '<span class="bad">PRESSED</span>' : '<span class="ok">released</span>';
  $("ctl-fault").textContent = c.fault == null ? "-" : c.fault + (c.last_fault_event ? ` (last event ${c.last_fault_event.fault})` : "");
  $("ctl-params").textContent = c.parameters || "-";
  const age = cmm.last_pose_at ? ` · last pose ${dur(Date.now() / 1000 - cmm.last_pose_at)} ago` : "";
  const err = cmm.last_error ? ` · <span class="bad">${esc(cmm.last_error)}</span>` : "";
  const what = cmm.kind === "tracker" ? "laser tracker " : "";
  $("cmm-link").innerHTML = `${esc(cmm.session || "-")}${age}${err} <span class="sub">${what}${esc(cmm.url || "")}</span>`;
}

function renderProgress() {
  const p = S().progress;
  if (!p) return;
  $("current-pose").textContent = p.pose ? `${p.phase} pose ${p.pose} of ${p.poses_in_phase}` : "-";
  $("activity").textContent = (p.phase_title ? p.phase_title + " · " : "") + (p.activity || "");
  $("done-count").textContent = `${p.done} of ${p.total}`;
  $("bar-fill").style.width = p.total ? `${(100 * p.done) / p.total}%` : "0";
  $("target").textContent = p.target ? p.target.map((v, i) => fmt(v, i < 3 ? 1 : 2)).join(", ") + "  (mm, deg)" : "-";
  tick();
}

function tick() {
  const p = S().progress, status = (S().run || {}).status;
  if (!p || !p.session_started_at) return;
  const now = Date.now() / 1000;
  const end = FINAL.includes(status) && S().result ? S().result.finished_at || now : now;
  $("elapsed").textContent = dur(end - p.session_started_at);
  const since = status === "running" && p.updated_at ? now - p.updated_at : 0;
  const left = p.remaining_s == null ? null : Math.max(0, p.remaining_s - since);
  const range = p.remaining_range_s;
  $("remaining").innerHTML = range ? `${dur(Math.max(0, range[0] - since))} to ${dur(Math.max(0, range[1] - since))} ` +
    `<span class="sub">(${esc(p.remaining_basis)})</span>` : left == null ?
    '<span class="sub">after the first pose</span>' : `${dur(left)} <span class="sub">(${esc(p.remaining_basis)})</span>`;
}

// ---------------------------------------------------------------- adaptive plan

function um(mm) {
  return mm == null ? "-" : `${fmt(mm * 1000, 1)} µm`;
}

function renderAdaptive() {
  const a = S().adaptive;
  $("adaptive-card").classList.toggle("hidden", !a);
  if (!a) return;
  const o = a.options || {};
  const p = a.prediction;
  $("adaptive-rows").textContent = a.n_rows ? `${a.n_rows} (${a.distinct} distinct poses)` : "none yet";
  $("adaptive-prediction").innerHTML = p ? `<b>${um(p.max_mm)}</b> median; 5-95 %: ${um(p.low_mm)} to ${um(p.upper_mm)}; ` +
    `<b>below ${um(p.upper_mm)}</b> with ${fmt(100 * p.confidence, 0)} % confidence` :
    '<span class="sub">no prediction before the rows identify the parameters</span>';
  $("adaptive-rule").textContent = (o.target_mm != null ? `the 95 % bound below the target ${um(o.target_mm)}` :
    "the 95 % bound improves by less than 5 % per row") + "; never before the diagnosis has its minimum; within " +
    (a.measure_budget_s != null ? `${dur(a.measure_budget_s)} of measuring` : "the budget");
  const f = a.forecast, range = a.remaining_measure_range_s;
  $("adaptive-remaining").textContent = a.stop ? "measure phase done" : range ?
    `${dur(range[0] + a.after_measure_s)} to ${dur(range[1] + a.after_measure_s)} (no noise known before the repeats)` :
    a.remaining_s != null ? `${dur(a.remaining_s)}: ${f.n_rows} more measure rows (${dur(a.remaining_measure_s)}), ` +
    `then the verify phases (${dur(a.after_measure_s)}); machine-time estimate` :
    o.best_rows != null ? `${dur(o.run_best_s)} to ${dur(o.run_worst_s)} before motion` : "-";
  $("adaptive-why").textContent = a.sentence || "-";
  $("adaptive-stop").classList.toggle("hidden", !a.stop);
  $("adaptive-stop").textContent = a.stop ? `Stopped: ${a.stop.kind.replace("_", " ")}. ${a.stop.sentence}` : "";
  const h = a.history || [];
  const svg = $("adaptive-plot");
  const last = Math.max(...h.map((r) => r.n_rows), 1);
  errorPlot(svg, [{ color: "var(--measure)", cls: "pt-adaptive",
    points: h.map((r) => [r.n_rows, r.max_mm, `row ${r.n_rows}: median ${um(r.max_mm)}`]) },
  { color: "var(--bad)", cls: "pt-bound", points: h.map((r) => [r.n_rows, r.upper_mm, `row ${r.n_rows}: 95 % bound ${um(r.upper_mm)}`]) }],
  last, "rows measured");
  if (h.length > 1) {
    const box = svg.viewBox.baseVal;
    const values = h.flatMap((r) => [r.max_mm, r.upper_mm]);
    const [d0, d1] = SVG.logDomain(values);
    const y = SVG.log(d0, d1, box.height - 20, 8), x = SVG.linear(0, last, 44, box.width - 8);
    SVG.el(svg, "polyline", { points: h.map((r) => `${x(r.n_rows)},${y(r.upper_mm)}`).join(" "), fill: "none",
      stroke: "var(--bad)", "stroke-width": 1.5, class: "adaptive-bound" });
  }
}

// ---------------------------------------------------------------- plots

// The workspace picture and the plan table are built once per plan; later changes only recolour a pose
// and move the "current" marks, so a long run does not redraw hundreds of elements per move.
const views = { sha: null, marks: new Map(), rows: new Map(), shown: new Set(), current: [] };

function planKey(phase, index) {
  return `${phase === "verify_after" ? "verify" : phase}:${index}`;
}

function buildPlanViews(plan) {
  views.sha = plan.sha256 + ":" + plan.measure.length;  // an adaptive run's measure poses grow as it chooses them
  views.marks = new Map();
  views.rows = new Map();
  views.shown = new Set();
  views.current = [];
  const svg = $("workspace");
  SVG.clear(svg);
  const w = plan.workspace, W = 280, H = 250, top = 20;
  for (const [a, b, na, nb, x0] of [[0, 1, "x", "y", 20], [0, 2, "x", "z", 340]]) {
    const sx = SVG.linear(w[a][0], w[a][1], x0 + 10, x0 + W), sy = SVG.linear(w[b][0], w[b][1], top + H, top);
    SVG.el(svg, "rect", { x: x0 + 10, y: top, width: W - 10, height: H, fill: "none", stroke: "#c5c9d2", "stroke-dasharray": "4 3" });
    SVG.el(svg, "text", { x: x0 + 10, y: 14 }, `${na}-${nb} (${fmt(w[a][0], 0)}..${fmt(w[a][1], 0)} × ${fmt(w[b][0], 0)}..${fmt(w[b][1], 0)} mm)`);
    for (const phase of ["measure", "verify"]) {
      const color = phase === "measure" ? "var(--measure)" : "var(--verify)";
      plan[phase].forEach((pose, i) => {
        const c = SVG.title(SVG.el(svg, "circle", { cx: sx(pose[a]), cy: sy(pose[b]), r: 4, stroke: color,
          "stroke-width": 1.5, fill: "#fff", "data-color": color }), `${phase} pose ${i + 1}`);
        const key = planKey(phase, i);
        views.marks.set(key, [...(views.marks.get(key) || []), c]);
      });
    }
  }
  const head = "<tr><th>pose</th><th>x mm</th><th>y mm</th><th>z mm</th><th>roll °</th><th>pitch °</th><th>yaw °</th>" +
    "<th>before mm</th><th>after mm</th></tr>";
  $("plan-table").innerHTML = head + ["measure", "verify"].flatMap((phase) => plan[phase].map((pose, i) =>
    `<tr data-key="${planKey(phase, i)}"><td>${phase} ${i + 1}</td>${pose.map((v, j) => `<td>${fmt(v, j < 3 ? 1 : 2)}</td>`).join("")}<td></td><td></td></tr>`)).join("");
  for (const row of $("plan-table").querySelectorAll("tr[data-key]")) views.rows.set(row.dataset.key, row);
  $("plan-sha").textContent = `${plan.robot} · plan sha256 ${plan.sha256.slice(0, 12)} · settle ${plan.settle_s} s · approach ${plan.approach_mm} mm`;
}

function renderPlan() {
  const plan = S().plan;
  if (!plan) return;
  if (views.sha !== plan.sha256 + ":" + plan.measure.length) buildPlanViews(plan);
  for (const m of S().measurements || []) {
    const id = `${m.phase}:${m.index}`;
    if (views.shown.has(id)) continue;
    views.shown.add(id);
    const key = planKey(m.phase, m.index), row = views.rows.get(key);
    if (row) {
      row.cells[m.phase === "verify_after" ? 8 : 7].textContent = fmt(m.position_error_mm, 4);
      row.classList.add("done");
    }
    for (const c of views.marks.get(key) || []) {
      c.setAttribute("fill", c.dataset.color);
      c.firstChild.textContent = `${m.phase} pose ${m.index + 1}: error ${fmt(m.position_error_mm, 4)} mm`;
    }
  }
  const p = S().progress || {};
  const current = p.pose ? planKey(p.phase, p.pose - 1) : null;
  if (views.current[0] === current) return;
  for (const node of views.current.slice(1)) node.remove();
  views.current = [current];
  if (!current) return;
  const row = views.rows.get(current);
  if (row) {
    row.classList.add("current");
    views.current.push({ remove: () => row.classList.remove("current") });
  }
  for (const c of views.marks.get(current) || []) {
    views.current.push(SVG.el($("workspace"), "circle", { cx: c.getAttribute("cx"), cy: c.getAttribute("cy"), r: 9,
      fill: "none", stroke: "var(--bad)", "stroke-width": 3, class: "current-marker" }));
  }
}

function errorPlot(svg, series, xmax, labelFor) {
  SVG.clear(svg);
  const box = svg.viewBox.baseVal, left = 44, right = box.width - 8, top = 8, bottom = box.height - 20;
  const values = series.flatMap((s) => s.points.map((pt) => pt[1]));
  const [d0, d1] = SVG.logDomain(values);
  const y = SVG.log(d0, d1, bottom, top), x = SVG.linear(0, Math.max(xmax, 1), left, right);
  SVG.logAxis(svg, d0, d1, y, left, right);
  SVG.el(svg, "text", { x: right, y: box.height - 4, "text-anchor": "end" }, labelFor);
  for (const s of series) {
    for (const [xi, v, tip] of s.points) {
      SVG.title(SVG.el(svg, "circle", { cx: x(xi), cy: y(v), r: 3, fill: s.color, class: s.cls }), tip);
    }
  }
}

function renderErrors() {
  const rows = S().measurements || [];
  const total = (S().progress || {}).total || rows.length;
  const byPhase = {};
  rows.forEach((m, k) => {
    (byPhase[m.phase] = byPhase[m.phase] || []).push([k, m.position_error_mm,
      `${m.phase} pose ${m.index + 1}: ${fmt(m.position_error_mm, 4)} mm, ${fmt(m.orientation_error_deg, 5)}°`]);
  });
  errorPlot($("errors"), Object.entries(byPhase).map(([phase, points]) => ({ color: PHASE_COLOR[phase], points, cls: "pt-" + phase })),
    total, "poses in the order measured (blue: measurement, orange: verification before, green: after)");
  const last = rows[rows.length - 1];
  $("last-measurement").textContent = last ? `last: ${last.phase} pose ${last.index + 1}, ` +
    `measured vs commanded ${fmt(last.position_error_mm, 4)} mm, ${fmt(last.orientation_error_deg, 5)}° ` +
    `(sphere fit RMS ${fmt(last.sphere_fit_rms_mm, 4)} mm)` : "-";
}

function renderVerification() {
  const rows = S().measurements || [];
  const before = rows.filter((m) => m.phase === "verify"), after = rows.filter((m) => m.phase === "verify_after");
  const n = ((S().plan || {}).verify || []).length || before.length;
  const pts = (list) => list.map((m) => [m.index, m.position_error_mm, `pose ${m.index + 1}: ${fmt(m.position_error_mm, 4)} mm`]);
  errorPlot($("verification"), [{ color: "var(--verify)", points: pts(before), cls: "pt-before" },
    { color: "var(--after)", points: pts(after), cls: "pt-after" }], n, "verification pose");
  const max = (list) => list.length ? Math.max(...list.map((m) => m.position_error_mm)) : null;
  const b = max(before), a = max(after);
  $("verification-summary").textContent = b === null ? "-" : `before: max ${fmt(b, 4)} mm (${before.length} poses)` +
    (a === null ? "" : `; after: max ${fmt(a, 4)} mm (${after.length} poses)` +
      (after.length === before.length ? `, ${fmt(100 * (1 - a / b), 1)} % lower` : ""));
}

// ---------------------------------------------------------------- tables and cards

function renderIdentification() {
  const id = S().identification;
  if (!id) {
    $("identification").textContent = "not yet";
    return;
  }
  const est = Object.entries(id.estimators).map(([name, e]) => `<tr><td>${name === id.chosen ? "<b>" + esc(name) + "</b> (chosen)" : esc(name)}</td>` +
    `<td>${fmt(e.max_residual_mm, 4)}</td><td>${fmt(e.rms_residual_mm, 4)}</td><td>${e.converged ? "yes" : '<span class="bad">no</span>'}</td>` +
    `<td>${fmt(e.verify_identified_model && e.verify_identified_model.max_position_mm, 4)}</td></tr>`).join("");
  const params = id.largest_parameters.map((p) => `<tr><td>${esc(p.name)}</td><td>${fmt(p.value_mm, 4)}</td><td>${p.std_mm == null ? "" : "± " + fmt(p.std_mm, 4)}</td></tr>`).join("");
  const problems = (id.problems || []).length ? `<p class="bad">refused: ${(id.problems || []).map(esc).join("; ")}</p>` : `<p class="ok">plausible (${esc(id.mode || "")})</p>`;
  $("identification").innerHTML = problems +
    `<table class="data"><tr><th>estimator</th><th>max resid. mm</th><th>RMS resid. mm</th><th>conv.</th><th>model on verify, max mm</th></tr>${est}</table>` +
    `<p class="sub">largest of ${id.n_parameters} parameters (${esc(id.chosen)}):</p><div class="scroll"><table class="data">${params}</table></div>`;
}

function renderUpload() {
  const u = S().upload;
  if (!u) return;
  const r = u.record || {};
  const good = (u.outcome === "saved" || u.outcome === "committed") && !/DIFFERS/.test(u.summary || "");
  $("upload").innerHTML = `<p>Upload: <b class="${good ? "ok" : "bad"}" id="upload-outcome">${esc(u.summary || u.outcome)}</b>` +
    ` <span class="sub">sha256 ${esc((u.sha256 || "").slice(0, 16))} · ${esc(r.endpoint || "")}</span></p>` +
    (u.sentences || []).map((line) => `<p class="sub">${esc(line)}</p>`).join("");
}

function renderResult() {
  const r = S().result, run = S().run || {};
  if (!r) {
    $("result").textContent = "-";
    return;
  }
  const links = (r.files || []).map((f) => `<a href="${q(`/runs/${run.run_id}/${f}`)}" target="_blank" id="link-${f.replace(/[^a-z]/g, "-")}">${esc(f)}</a>`).join(" · ");
  const v = r.verification || {}, cert = r.certificate;
  const signoff = cert ? `<p id="result-verdict" class="${cert.verdict === "fail" ? "bad" : cert.verdict === "pass" ? "ok" : ""}">` +
    `acceptance verdict: <b>${esc(cert.verdict)}</b> · certificate ${esc(cert.number)}</p>` : "";
  $("result").innerHTML = `<p id="result-message" class="${r.code === 0 ? "ok" : "bad"}">${esc(r.message)}</p>` + signoff +
    (v.before ? `<table class="kv"><tr><th>before</th><td>${brief(v.before)}</td></tr><tr><th>after</th><td id="result-after">${brief(v.after)}</td></tr></table>` : "") +
    `<p>${links}</p>` + ((r.files || []).includes("recording.csv") ? '<button id="diagnose">Run diagnosis on this recording</button>' : "");
  const button = $("diagnose");
  if (button) button.onclick = () => post(`/api/runs/${run.run_id}/diagnose`).catch((e) => ($("diagnosis").textContent = e.message));
}

function renderDiagnosis() {
  const d = S().diagnosis;
  if (!d) return;
  if (d.status !== "done") {
    $("diagnosis").innerHTML = d.status === "running" ? `diagnosing run ${esc(d.run_id)}…` : `<span class="bad">${esc(d.error)}</span>`;
    return;
  }
  $("diagnosis").innerHTML = `<p><b id="diagnosis-effect">${esc(d.effect)}</b> <span class="sub">run ${esc(d.run_id)}</span></p>` +
    `<p>${esc(d.explanation)}</p><table class="kv"><tr><th>geometry only</th><td>${brief(d.before)}</td></tr>` +
    `<tr><th>with the effect</th><td>${brief(d.after)}</td></tr></table>` +
    `<ul>${(d.findings || []).map((f) => `<li>${esc(f)}</li>`).join("")}</ul><a href="${q(d.report_url)}" target="_blank">diagnosis report</a>`;
}

function renderTimeline() {
  const items = (S().timeline || []).slice(-60).reverse();
  $("timeline").innerHTML = items.map((it) => `<li class="${esc(it.level)}">${new Date(it.t * 1000).toLocaleTimeString()} ${esc(it.text)}</li>`).join("");
}

// ---------------------------------------------------------------- history

async function loadHistory(machine = null) {
  const r = await fetch(q("/api/history" + (machine ? `?machine=${encodeURIComponent(machine)}` : "")));
  const h = await r.json();
  $("history-source").textContent = (h.records ? `records ${h.records}` : "no records database") + (h.note ? ` (${h.note})` : "");
  $("machines").innerHTML = '<option value="">all machines</option>' + (h.machines || []).map((m) =>
    `<option value="${esc(m.machine)}"${m.machine === machine ? " selected" : ""}>${esc(m.machine)} (${m.runs} runs)</option>`).join("");
  const head = "<tr><th>time (UTC)</th><th>run / operation</th><th>status</th><th>machine</th><th>operator</th><th>est.</th>" +
    "<th>max before mm</th><th>max after mm</th><th>uploads</th><th>files</th></tr>";
  const rows = h.entries.map((e) => {
    if (e.kind === "upload") {
      return `<tr class="upload"><td>${esc(e.time)}</td><td>${esc((e.record || {}).operation || "upload")}</td><td>${esc(e.outcome)}</td>` +
        `<td>${esc(e.endpoint)}</td><td>${esc(e.operator)}</td><td></td><td></td><td></td><td>sha256 ${esc((e.params_sha256 || "").slice(0, 12))}</td><td></td></tr>`;
    }
    const ups = (e.uploads || []).map((u) => `${esc(u.outcome)} ${esc((u.params_sha256 || "").slice(0, 8))}`).join(", ");
    const files = (e.files || []).map((f) => `<a href="${q(`/runs/${e.run_id}/${f}`)}" target="_blank">${esc(f)}</a>`).join(" ");
    const verdict = e.verdict ? ` · <b class="verdict ${e.verdict === "fail" ? "bad" : e.verdict === "pass" ? "ok" : ""}">${esc(e.verdict)}</b>` : "";
    return `<tr class="run" data-run="${esc(e.run_id)}"><td>${esc(e.started_at)}</td><td>${esc(e.run_id)}</td><td>${esc(e.status)}${verdict}</td>` +
      `<td><a href="#" class="machine-link" data-machine="${esc(e.machine || "")}">${esc(e.machine || e.robot_name)}</a></td><td>${esc(e.operator)}</td><td>${esc(e.estimator)}</td>` +
      `<td>${fmt(e.verify_before && e.verify_before.max_position_mm, 4)}</td><td>${fmt(e.verify_after && e.verify_after.max_position_mm, 4)}</td>` +
      `<td>${ups}</td><td>${files}</td></tr>`;
  });
  $("history-table").innerHTML = head + (rows.join("") || '<tr><td colspan="10">no runs recorded</td></tr>');
  document.querySelectorAll(".machine-link").forEach((a) => (a.onclick = (ev) => {
    ev.preventDefault();
    if (a.dataset.machine) showMachine(a.dataset.machine);
  }));
  if (machine) loadDrift(machine).catch((e) => ($("drift").textContent = e.message));
}

function showMachine(machine) {
  loadHistory(machine).catch((e) => ($("history-source").textContent = e.message));
}

async function loadDrift(machine) {
  $("drift").textContent = `drift of ${machine}…`;
  const r = await fetch(q(`/api/drift?machine=${encodeURIComponent(machine)}`));
  const d = await r.json();
  if (!r.ok) throw new Error(d.error || r.statusText);
  const since = (d.since_last || []).map((s) => `<li>${esc(s)}</li>`).join("") || "<li>no parameter moved beyond the rule</li>";
  const flags = (d.flags || []).map((s) => `<li class="bad">${esc(s)}</li>`).join("") || "<li>nothing flagged</li>";
  $("drift").innerHTML = `<p><b id="drift-machine">${esc(d.machine)}</b>: ${d.n_calibrations} calibrations. <span class="sub">${esc(d.rule)}</span></p>` +
    `<p>since the previous calibration:</p><ul id="drift-since">${since}</ul><p>over the history:</p><ul id="drift-flags">${flags}</ul>` +
    (d.plot_png ? `<img id="drift-plot" alt="parameter trends" src="data:image/png;base64,${d.plot_png}">` : "<p>fewer than two calibrations: no trend yet</p>");
}

function showView(name) {
  for (const v of ["run", "history"]) {
    $("view-" + v).classList.toggle("hidden", v !== name);
    $("tab-" + v).classList.toggle("active", v === name);
  }
  if (name === "history") loadHistory().catch((e) => ($("history-source").textContent = e.message));
}

// ---------------------------------------------------------------- wiring

document.querySelectorAll(".tab").forEach((t) => (t.onclick = () => showView(t.dataset.view)));
$("question-yes").onclick = () => answer(true);
$("question-no").onclick = () => answer(false);
$("upload-confirm").onchange = (e) => ($("question-yes").disabled = !e.target.checked);
$("pause").onclick = () => command("pause");
$("continue").onclick = () => command("continue");
$("abort").onclick = () => command("abort");
$("close-panel").onclick = () => command("close");
$("machines").onchange = (e) => showMachine(e.target.value || null);
setInterval(() => {
  tick();
  renderStation();
}, 1000);
connect();
