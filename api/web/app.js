// phasecal operator page: plain JS against the REST API (same token as the API).
"use strict";

const $ = (sel) => document.querySelector(sel);
const state = { session: null, job: null, source: null, suggestion: null };

function token() { return localStorage.getItem("phasecal_token") || ""; }

function setToken(value) {
  localStorage.setItem("phasecal_token", value);
  // Images, reports and the SSE stream are loaded by URL and cannot send a header:
  // the server accepts this cookie for GET requests only.
  document.cookie = "phasecal_token=" + encodeURIComponent(value) + "; path=/; SameSite=Strict";
}

function say(text, error) {
  const el = $("#status");
  el.textContent = text;
  el.className = error ? "error" : "";
}

async function api(method, path, body) {
  const headers = {};
  if (token()) headers["Authorization"] = "Bearer " + token();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers,
                                body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) {
    let detail = r.statusText;
    try { detail = (await r.json()).detail || detail; } catch (e) { /* not JSON */ }
    const err = new Error(`${method} ${path}: ${r.status} ${detail}`);
    err.status = r.status;
    throw err;
  }
  return r.json();
}

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "onclick") node.onclick = v; else node.setAttribute(k, v);
  }
  for (const c of children) node.append(c instanceof Node ? c : String(c));
  return node;
}

function fmt(v, digits) { return v === null || v === undefined ? "-" : Number(v).toPrecision(digits || 4); }

// --- rigs and their live camera preview ------------------------------------------------
function previewBox(rig) {
  const box = el("div", { class: "preview", "data-rig": rig.id });
  const img = el("img", { alt: `camera of ${rig.name}` });
  const none = el("span", { class: "no-preview" }, "no preview");
  box.append(none);
  const tryLoad = () => {
    img.onload = () => { none.remove(); if (!img.isConnected) box.append(img); };
    img.onerror = () => {
      img.remove();
      if (!none.isConnected) box.append(none);
      none.textContent = "no preview (the camera preview is not available)";
      setTimeout(tryLoad, 15000);
    };
    img.src = `/rigs/${rig.id}/camera/preview?ts=${Date.now()}`;
  };
  // An MJPEG stream never finishes loading: start it after the page's load event, which it
  // would otherwise hold back forever.
  if (document.readyState === "complete") tryLoad();
  else window.addEventListener("load", tryLoad, { once: true });
  return box;
}

async function loadRigs() {
  const rigs = await api("GET", "/rigs");
  const box = $("#rigs");
  box.replaceChildren(...rigs.map((r) => el("div", { class: "rig" },
    el("div", {}, el("b", {}, r.name || r.id), ` (${r.simulated ? "simulated" : "hardware"}, ${r.id})`),
    previewBox(r))));
  $("#new-session-rig").replaceChildren(...rigs.map((r) => el("option", { value: r.id }, r.name || r.id)));
}

// --- sessions -----------------------------------------------------------------------------
async function loadSessions() {
  const sessions = await api("GET", "/sessions");
  $("#sessions").replaceChildren(...sessions.map((s) => {
    const li = el("li", { "data-session": s.id, onclick: () => openSession(s.id) },
                  `${s.name || "(unnamed)"} — ${s.id}`);
    if (state.session === s.id) li.classList.add("current");
    return li;
  }));
}

async function openSession(id) {
  state.session = id;
  const s = await api("GET", `/sessions/${id}`);
  $("#session-section").hidden = false;
  $("#session-title").textContent = `Session ${s.name || ""} (${id})`;
  await Promise.all([loadSessions(), refreshSession()]);
}

async function refreshSession() {
  if (!state.session) return;
  await Promise.all([loadPoses(), loadCalibrations()]);
  await loadNextPose();
}

async function loadPoses() {
  const sid = state.session;
  const poses = await api("GET", `/sessions/${sid}/poses`);
  const rows = poses.map((p) => el("tr", { "data-pose": p.id },
    el("td", {}, p.index), el("td", {}, p.id),
    el("td", { class: p.status === "ready" ? "" : "bad" }, p.status + (p.error ? `: ${p.error}` : "")),
    el("td", {}, p.valid_pixels ?? "-"),
    el("td", {}, ["ready", "flagged"].includes(p.status)
      ? el("button", { onclick: () => showMaps(p.id) }, "show maps") : "-")));
  $("#poses tbody").replaceChildren(...rows);
  const decoded = poses.filter((p) => ["ready", "flagged"].includes(p.status)).length;
  const cov = $("#coverage");
  cov.hidden = decoded === 0;
  if (decoded) cov.src = `/sessions/${sid}/coverage.png?n=${decoded}&ts=${Date.now()}`;
}

function showMaps(poseId) {
  const base = `/sessions/${state.session}/poses/${poseId}/preview`;
  $("#pose-maps").replaceChildren(el("h4", {}, `Decoded maps of ${poseId}`),
    ...["x", "y", "sigma", "mask"].map((k) => el("img", { src: `${base}/${k}.png`, alt: `${k} map` })));
}

// --- capture with progress from the SSE stream --------------------------------------------
function follow(job, onEnd) {
  state.job = job.id;
  $("#cancel-btn").disabled = false;
  $("#capture-btn").disabled = true;
  showProgress(job);
  // EventSource reconnects by itself and sends Last-Event-ID; the server resumes from it.
  const source = new EventSource(`/jobs/${job.id}/events`);
  state.source = source;
  source.addEventListener("progress", (e) => showProgress(JSON.parse(e.data)));
  source.addEventListener("end", (e) => {
    source.close();
    const end = JSON.parse(e.data);
    showProgress(end);
    state.job = null;
    $("#cancel-btn").disabled = true;
    $("#capture-btn").disabled = false;
    onEnd(end);
  });
}

function showProgress(job) {
  const bar = $("#progress");
  const total = Math.max(job.total || 0, 1);
  bar.max = total;
  bar.value = job.status === "succeeded" ? total : Math.min(job.done || 0, total);
  const eta = job.eta_s ? `, ${job.eta_s.toFixed(0)} s left in this stage` : "";
  const err = job.error ? ` — ${job.error}` : "";
  $("#progress-text").textContent = `${job.kind} ${job.status}: ${job.stage} ${job.done}/${job.total}${eta}${err}`;
  $("#progress-text").dataset.status = job.status;
}

async function capture() {
  const body = {};
  if ($("#use-suggestion").checked && state.suggestion) body.screen_pose = state.suggestion.screen_pose;
  const job = await api("POST", `/sessions/${state.session}/poses`, body);
  say(`capture ${job.id} started`);
  await loadPoses();
  follow(job, async (end) => { say(`capture ${end.status}`, end.status !== "succeeded"); await refreshSession(); });
}

async function cancel() {
  if (state.job) await api("POST", `/jobs/${state.job}/cancel`);
}

// --- calibrations and their reports -------------------------------------------------------
async function loadCalibrations() {
  const cals = await api("GET", `/calibrations?session_id=${state.session}`);
  $("#calibrations tbody").replaceChildren(...cals.map((c) => el("tr", { "data-calibration": c.id },
    el("td", {}, c.id), el("td", {}, c.model),
    el("td", { class: c.status === "succeeded" ? "" : "bad" }, c.status + (c.error ? `: ${c.error}` : "")),
    el("td", {}, fmt(c.stats && c.stats.rms_px)), el("td", {}, fmt(c.stats && c.stats.noise_floor_ratio, 3)),
    el("td", {}, c.status === "succeeded"
      ? el("a", { href: `/calibrations/${c.id}/report.html`, target: "_blank", class: "report-link" }, "report")
      : "-"))));
}

async function calibrate(ev) {
  ev.preventDefault();
  const job = await api("POST", `/sessions/${state.session}/calibrations`, { model: $("#calibrate-model").value });
  say(`calibration ${job.id} started`);
  await loadCalibrations();
  follow(job, async (end) => { say(`calibration ${end.status}`, end.status !== "succeeded"); await loadCalibrations(); });
}

// --- the suggested next pose --------------------------------------------------------------
async function loadNextPose() {
  const text = $("#next-pose-text");
  const img = $("#next-pose-img");
  try {
    const chosen = $("#calibrate-model").value;
    const model = ["opencv5", "opencv-rational", "fisheye"].includes(chosen) ? chosen : "opencv-rational";
    const g = await api("GET", `/sessions/${state.session}/next-pose?model=${model}`);
    state.suggestion = g;
    const p = g.predicted_worst_ray_sigma_urad;
    const [u, v] = g.screen_center_px;
    text.textContent = `Predicted with ${g.model}, from ${g.poses_used.length} poses. Screen at ${g.distance_mm.toFixed(0)} mm, tilted ${g.tilt_deg.toFixed(0)} deg ` +
      `towards ${g.tilt_azimuth_deg.toFixed(0)} deg, its centre at pixel (${u.toFixed(0)}, ${v.toFixed(0)}), ` +
      `filling ${(100 * g.image_fraction).toFixed(0)}% of the image. Worst predicted ray sigma ` +
      `${fmt(p.now, 3)} urad now, ${fmt(p.after, 3)} urad after it.`;
    img.src = g.image;
    img.hidden = false;
  } catch (e) {
    state.suggestion = null;
    img.hidden = true;
    text.textContent = e.status === 409 ? "capture at least 3 varied poses first" : e.message;
  }
}

// --- wiring ---------------------------------------------------------------------------------
function guard(fn) {
  return async (...args) => {
    try { await fn(...args); } catch (e) { say(e.message, true); }
  };
}

async function start() {
  $("#token").value = token();
  if (token()) setToken(token());
  await loadRigs();
  await loadSessions();
  say("ready");
}

$("#token-form").onsubmit = guard(async (ev) => { ev.preventDefault(); setToken($("#token").value); await start(); });
$("#new-session").onsubmit = guard(async (ev) => {
  ev.preventDefault();
  const s = await api("POST", "/sessions", { name: $("#new-session-name").value,
    rig_id: $("#new-session-rig").value || null, preset: $("#new-session-preset").value });
  await openSession(s.id);
});
$("#capture-btn").onclick = guard(capture);
$("#cancel-btn").onclick = guard(cancel);
$("#calibrate-form").onsubmit = guard(calibrate);
$("#calibrate-model").onchange = guard(async () => { if (state.session) await loadNextPose(); });
guard(start)();
