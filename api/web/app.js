// phasecal operator page: plain JS against the REST API (same token as the API).
// A newcomer goes from a new session through varied starting poses, guided poses and a
// calibration to the report and the model files, and every action answers next to itself.
// Modules: service.js (requests, explanations), dom.js, camera_view.js (a preview per camera).

import { $, el, fmt } from "/ui/dom.js";
import { CameraView, rigCameras } from "/ui/camera_view.js";
import { ServiceError, api, explain, explainJob, request, setToken, token } from "/ui/service.js";
import { autoBody, autoLog, hasMover } from "/ui/auto_panel.js";
import { isRigCalibration, modelChoosers, poseCameraCell, rigCalibrationBody, rigDownloads,
         rigMaps, rigNextPose, rigResult } from "/ui/rig_panel.js";

const STARTING_COUNT = 5;      // starting poses asked for: enough for guidance and opencv fits
const EXPORT_FORMATS = [       // the REST export formats and what each is for
  ["opencv-yaml", "OpenCV YAML", "cv2.FileStorage: camera_matrix, distortion_coefficients"],
  ["ros", "ROS camera_info", "sensor_msgs/CameraInfo YAML for camera_info_manager"],
  ["mrcal", "mrcal .cameramodel", "mrcal and its tools (generic models as a spline fit)"],
  ["remap", "cv2.remap maps (NPZ)", "map_x, map_y into a virtual pinhole camera"],
  ["opencv-fit", "best OpenCV fit (NPZ)", "the closest OpenCV model, with its residual per pixel"],
];

const state = {
  rigs: new Map(),          // rig id -> rig record
  session: null,            // the open session's record
  rig: null,                // its rig
  cameras: new Map(),       // camera name -> CameraView (one per camera of the rig)
  poses: [],
  calibrations: [],
  heldout: new Set(),       // pose ids held out of the next calibration
  starting: [],             // the session's starting poses
  suggestion: null,         // the next-pose answer
  calibration: null,        // the calibration whose downloads are shown
  busy: false,              // a capture or calibration job is being followed
  capturing: false,         // that job is a capture (the preview shows its frames)
  job: null,                // its id (for Cancel)
  variety: null,            // the pose-variety answer: duplicates, readiness
  assumedCamera: null,      // the camera the starting poses were planned for
  nextPoseAsked: 0,         // counts next-pose requests: a slow older answer is dropped
};

function say(text, error) {
  const s = $("#status");
  s.textContent = text;
  s.className = error ? "error" : "";
}

// Feedback next to the action that caused it: a sentence, and the service's own words.
function tell(id, kind, text, err) {
  const box = document.getElementById(id);
  box.className = `feedback ${kind}`;
  box.replaceChildren(el("span", { class: "message" }, text));
  if (err instanceof ServiceError && err.detail) {
    box.append(el("details", {}, el("summary", {}, "what the service said"),
                  el("code", {}, `${err.status} ${err.slug}: ${err.detail}`)));
  }
}

function clear(id) { const box = document.getElementById(id); box.className = "feedback"; box.replaceChildren(); }

// Run an action; a failure is explained in its own feedback box.
function act(feedbackId, fn) {
  return async (...args) => {
    try { await fn(...args); } catch (e) { tell(feedbackId, "error", explain(e), e); }
  };
}

// --- URL state: the open session, pose and calibration ------------------------------------
function urlState() {
  const q = new URLSearchParams(location.search);
  return { session: q.get("session"), pose: q.get("pose"), calibration: q.get("calibration") };
}

function setUrl(changes) {
  const q = new URLSearchParams(location.search);
  for (const [k, v] of Object.entries(changes)) { if (v) q.set(k, v); else q.delete(k); }
  const s = q.toString();
  history.replaceState(null, "", location.pathname + (s ? "?" + s : ""));
}

// --- cameras: a live preview per camera, with the suggested placement drawn over it --------
function showCameras(rig) {
  for (const view of state.cameras.values()) view.stop();
  state.cameras.clear();
  const cams = rigCameras(rig);
  for (const cam of cams) state.cameras.set(cam.name, new CameraView(rig, cam, cams.length > 1, () => state.capturing));
  $("#cameras").replaceChildren(...[...state.cameras.values()].map((v) => v.node));
  for (const view of state.cameras.values()) view.start();
}

function outlineOnCameras(points, label) {
  for (const view of state.cameras.values()) view.setOutline(points, label);
}

// --- rigs and sessions ---------------------------------------------------------------------
async function loadRigs() {
  const rigs = await api("GET", "/rigs");
  state.rigs = new Map(rigs.map((r) => [r.id, r]));
  $("#new-session-rig").replaceChildren(...rigs.map((r) => el("option", { value: r.id },
    `${r.name || r.id} (${r.simulated ? "simulated" : "hardware"})`)));
  showSimHint();
}

function showSimHint() {
  const rig = state.rig || state.rigs.get($("#new-session-rig").value);
  $("#sim-hint").hidden = !(rig && rig.simulated);
}

async function loadSessions() {
  const sessions = await api("GET", "/sessions");
  $("#sessions").replaceChildren(...sessions.map((s) => {
    const current = state.session && state.session.id === s.id;
    return el("li", { "data-session": s.id, class: current ? "current" : null },
      el("button", { class: "link", onclick: act("new-session-feedback", () => openSession(s.id)),
                     "aria-current": current ? "true" : null },
         `${s.name || "(unnamed)"} — ${s.id}`));
  }));
}

async function openSession(id) {
  const s = await api("GET", `/sessions/${id}`);
  if (!state.session || state.session.id !== id) {
    if (state.session) setUrl({ pose: null, calibration: null });  // they belong to the old one
    delete $("#pose-maps").dataset.pose;
    state.heldout.clear();
    state.calibration = null;
    state.suggestion = null;
    $("#pose-maps").replaceChildren();
    $("#calibration-detail").hidden = true;
    for (const id2 of ["capture-feedback", "starting-feedback", "calibrate-feedback",
                       "poses-feedback", "calibrations-feedback"]) clear(id2);
  }
  state.session = s;
  state.rig = state.rigs.get(s.rig_id) || (s.rig_id ? await api("GET", `/rigs/${s.rig_id}`) : null);
  setUrl({ session: id });
  $("#session-section").hidden = false;
  const rigName = state.rig ? `${state.rig.name} (${state.rig.simulated ? "simulated" : "hardware"})`
    : "the server's rig";
  $("#session-title").textContent = `Session ${s.name || ""} (${id}) on ${rigName}`;
  const places = placesScreen(state.rig);
  $("#starting-btn").hidden = !places;
  $("#use-suggestion-label").hidden = !places;
  showSimHint();
  if (state.rig) showCameras(state.rig);
  showRigModels();
  $("#auto-panel").hidden = !hasMover(state.rig);
  $("#auto-log").replaceChildren();
  await Promise.all([loadSessions(), refreshSession(), loadAutoLog()]);
}

// The rig's cameras when the session's rig has several (else null).
function rigCameraNames() {
  const names = state.rig ? rigCameras(state.rig).map((c) => c.name) : [];
  return names.length > 1 ? names : null;
}

function showRigModels() {
  const names = rigCameraNames();
  $("#rig-models").hidden = !names;
  $("#rig-models").replaceChildren(...(names ? modelChoosers(names, $("#calibrate-model").value) : []));
  $("#calibrate-model").hidden = !!names;
  $("label[for=calibrate-model]").hidden = !!names;
  $("#calibrate-btn").textContent = names ? "Calibrate rig" : "Calibrate";
}

async function refreshSession() {
  if (!state.session) return;
  await Promise.all([loadPoses(), loadCalibrations()]);
  loadNextPose();  // a fit on first request: the rest of the page does not wait for it
  await Promise.all([loadStarting(), loadVariety()]);
}

// --- poses ---------------------------------------------------------------------------------
const BAD_POSE = ["failed", "cancelled", "interrupted", "flagged"];  // shown in red

async function loadPoses() {
  const sid = state.session.id;
  state.poses = await api("GET", `/sessions/${sid}/poses`);
  const rows = state.poses.map((p) => {
    const decoded = ["ready", "flagged"].includes(p.status);
    const held = el("input", { type: "checkbox", "aria-label": `hold out pose ${p.index}`,
                               disabled: p.status !== "ready" });
    held.checked = state.heldout.has(p.id);
    held.onchange = () => { if (held.checked) state.heldout.add(p.id); else state.heldout.delete(p.id); showHeldout(); };
    return el("tr", { "data-pose": p.id },
      el("td", {}, p.index), el("td", {}, p.id),
      el("td", { class: BAD_POSE.includes(p.status) ? "bad" : "" }, p.status + (p.error ? `: ${p.error}` : "")),
      el("td", {}, poseCameraCell(p)),
      el("td", {}, held),
      el("td", {}, decoded ? el("button", { onclick: () => showMaps(p.id) }, "show maps") : "-"),
      el("td", {}, el("button", { class: "danger", "aria-label": `delete pose ${p.index}`,
                                  onclick: act("poses-feedback", () => deletePose(p)) }, "delete")));
  });
  $("#poses tbody").replaceChildren(...rows);
  for (const id of [...state.heldout]) if (!state.poses.some((p) => p.id === id && p.status === "ready")) state.heldout.delete(id);
  showHeldout();
  const decoded = state.poses.filter((p) => ["ready", "flagged"].includes(p.status));
  const cov = $("#coverage");
  cov.hidden = decoded.length === 0;
  if (decoded.length) cov.src = `/sessions/${sid}/coverage.png?poses=${decoded.map((p) => p.index).join("-")}`;
  const shown = urlState().pose;
  if (shown && decoded.some((p) => p.id === shown) && !$("#pose-maps").dataset.pose) showMaps(shown);
}

// A pose by its number in the session (ids are long), or its id when unknown here.
function poseName(id) {
  const p = state.poses.find((q) => q.id === id);
  return p ? String(p.index) : id;
}

function showHeldout() {
  const ready = state.poses.filter((p) => p.status === "ready").length;
  const held = state.heldout.size;
  $("#heldout-summary").textContent = held
    ? `fits ${ready - held} poses; ${held} held out to score it (ticked in the pose table)`
    : `fits all ${ready} ready poses (tick "held out" in the pose table to keep some for scoring)`;
}

function showMaps(poseId) {
  const base = `/sessions/${state.session.id}/poses/${poseId}/preview`;
  const box = $("#pose-maps");
  const pose = state.poses.find((p) => p.id === poseId);
  box.dataset.pose = poseId;
  setUrl({ pose: poseId });
  box.replaceChildren(el("h4", {}, `Decoded maps of ${poseId}`),
    el("p", { class: "explain" }, "x and y: the screen pixel each camera pixel sees; sigma: " +
       "how uncertain that is; mask: where the screen was decoded at all."),
    ...(pose && pose.cameras ? rigMaps(base, pose)
      : ["x", "y", "sigma", "mask"].map((k) => el("img", { src: `${base}/${k}.png`, alt: `${k} map of ${poseId}` }))));
}

async function deletePose(p) {
  if (!confirm(`Delete pose ${p.index} (${p.id}) and its frames and maps?`)) return;
  await api("DELETE", `/sessions/${state.session.id}/poses/${p.id}`);
  if ($("#pose-maps").dataset.pose === p.id) { $("#pose-maps").replaceChildren(); delete $("#pose-maps").dataset.pose; setUrl({ pose: null }); }
  clear("capture-feedback");  // it may speak of the deleted pose
  tell("poses-feedback", "ok", `Pose ${p.index} deleted.`);
  await refreshSession();
}

// --- jobs: progress next to the action that started them -----------------------------------
const PANELS = {
  capture: { bar: "#progress", text: "#progress-text", box: "#capture-job", cancel: "#cancel-btn" },
  calibrate: { bar: "#cal-progress", text: "#cal-progress-text", box: "#calibrate-job", cancel: "#cal-cancel-btn" },
  auto: { bar: "#auto-progress", text: "#auto-progress-text", box: "#auto-job", cancel: "#auto-cancel-btn" },
};

function setBusy(busy, jobId, panel) {
  state.busy = busy;
  state.capturing = busy && panel === PANELS.capture;
  state.job = busy ? jobId : null;
  for (const p of Object.values(PANELS)) $(p.cancel).disabled = !(busy && p === panel);
  for (const b of ["#capture-btn", "#calibrate-btn", "#new-session-btn", "#auto-btn"]) $(b).disabled = busy;
  $("#starting-btn").disabled = busy || !state.starting.some((p) => !p.captured_by);
  for (const b of document.querySelectorAll(".capture-one")) b.disabled = busy;
}

function showProgress(panel, job, label) {
  const bar = $(panel.bar);
  const total = Math.max(job.total || 0, 1);
  bar.max = total;
  bar.value = job.status === "succeeded" ? total : Math.min(job.done || 0, total);
  const eta = job.eta_s ? `, about ${job.eta_s.toFixed(0)} s left in this step` : "";
  const text = $(panel.text);
  const stage = job.stage && job.stage !== job.status ? ` (${job.stage})` : "";
  text.textContent = `${label || job.kind}: ${job.status}${stage} ${job.done}/${job.total}${eta}`;
  text.dataset.status = job.status;
}

// Follow a job's SSE stream until it ends; resolves with its final state.
function follow(job, panel, label) {
  setBusy(true, job.id, panel);
  showProgress(panel, job, label);
  $(panel.box).scrollIntoView({ block: "nearest" });
  return new Promise((resolve) => {
    // EventSource reconnects by itself and sends Last-Event-ID; the server resumes from it.
    const source = new EventSource(`/jobs/${job.id}/events`);
    source.addEventListener("progress", (e) => showProgress(panel, JSON.parse(e.data), label));
    source.addEventListener("end", (e) => {
      source.close();
      const end = JSON.parse(e.data);
      showProgress(panel, end, label);
      setBusy(false);
      resolve(end);
    });
  });
}

async function cancel() { if (state.job) await api("POST", `/jobs/${state.job}/cancel`); }

// --- capture -------------------------------------------------------------------------------
// `planNext`: ask for the next-pose plan afterwards (a fit; not between starting poses).
async function captureAt(screenPose, label, feedbackId, planNext = true) {
  const body = screenPose ? { screen_pose: screenPose } : {};
  const job = await api("POST", `/sessions/${state.session.id}/poses`, body);
  tell(feedbackId, "info", `${label || "Capture"} started (${job.id}).`);
  await loadPoses();
  const end = await follow(job, PANELS.capture, label || "Capture");
  // What the new pose means comes first; the next-pose plan (a fit) follows when ready.
  await Promise.all([loadPoses(), loadVariety(), loadStarting()]);
  if (planNext) loadNextPose();
  if (end.status !== "succeeded") {
    tell(feedbackId, "error", explainJob(end));
    return false;
  }
  // a refusal to calibrate (too few poses) said before this pose no longer holds
  if ($("#calibrate-feedback").classList.contains("error")) clear("calibrate-feedback");
  const pose = (end.resource || "").split("/").pop();
  const rec = state.poses.find((p) => p.id === pose);
  const repeat = state.variety && state.variety.duplicates.find((d) => d.pose_id === pose);
  if (repeat) {
    tell(feedbackId, "warn", `Pose ${rec ? rec.index : pose} repeats pose ${poseName(repeat.repeats)} ` +
         `(${(100 * repeat.similarity).toFixed(0)}% alike): it adds almost nothing. Move or ` +
         "tilt the screen and capture again, or delete it.");
  } else if (rec && rec.status === "flagged") {
    tell(feedbackId, "warn", `Pose ${rec.index} was captured but flagged: ${rec.error}. ` +
         "Capture it again with the screen and camera still.");
  } else {
    tell(feedbackId, "ok", `${label || "Capture"} succeeded: pose ${rec ? rec.index : pose}` +
         (rec && rec.valid_pixels ? ` sees the screen on ${rec.valid_pixels} pixels.` : "."));
  }
  return true;
}

async function captureClicked() {
  const pose = $("#use-suggestion").checked && state.suggestion ? state.suggestion.screen_pose : null;
  await captureAt(pose, pose ? "Capture at the suggested pose" : "Capture", "capture-feedback");
}

// --- starting poses and pose variety -------------------------------------------------------
// The page places the screen itself only on a simulated rig without a mover: with one, the
// view follows the robot (the automatic run moves it), as on hardware.
function placesScreen(rig) { return !!(rig && rig.simulated && !hasMover(rig)); }

async function loadStarting() {
  const list = $("#starting-list");
  try {
    const answer = await api("GET", `/sessions/${state.session.id}/starting-poses?count=${STARTING_COUNT}`);
    state.starting = answer.poses;
    state.assumedCamera = answer.camera || null;
    if (answer.camera) {
      const [w, h] = answer.camera.image_size;
      for (const view of state.cameras.values()) view.assumeSize(w, h);
    }
  } catch (e) {
    state.starting = [];
    list.replaceChildren();
    tell("starting-feedback", "error", explain(e), e);
    return;
  }
  const places = placesScreen(state.rig);
  const open = state.starting.filter((p) => !p.captured_by);
  $("#starting-btn").textContent = !open.length ? "All starting poses captured"
    : open.length === state.starting.length ? `Capture the ${state.starting.length} starting poses`
      : `Capture the ${open.length} remaining starting poses`;
  $("#starting-btn").disabled = state.busy || open.length === 0;
  $("#starting-text").textContent = places
    ? "A calibration needs the screen seen from varied places. On the simulated rig the page " +
      "moves the screen through this varied set for you: capture them all, or one by one."
    : hasMover(state.rig)
      ? "A calibration needs the screen seen from varied places. This rig's robot carries the " +
        "camera or the screen: the automatic run below moves it through varied poses and " +
        "captures them. Or move the robot so the screen lies where a line's outline shows, " +
        "then press Capture."
      : "A calibration needs the screen seen from varied places. Put the screen where each " +
        "line says (the dashed outline on the camera preview shows it), then press Capture.";
  if (state.assumedCamera) {
    $("#starting-text").append(el("span", { class: "explain", title: "what the plan assumed about the camera" },
      ` Planned for ${state.assumedCamera.assumed}.`));
  }
  list.replaceChildren(...state.starting.map((p, i) => {
    const done = p.captured_by
      ? el("span", { class: "ok" }, ` captured (${p.captured_by})`)
      : places
        ? el("button", { class: "capture-one", disabled: state.busy,
                         onclick: act("starting-feedback", () => captureAt(p.screen_pose, `Starting pose ${i + 1}`, "starting-feedback")) },
             "capture this one")
        : el("button", { onclick: () => outlineOnCameras(p.outline_px, `starting pose ${i + 1}`) }, "show outline");
    return el("li", { "data-captured": p.captured_by ? "yes" : "no" }, p.placement, " ", done);
  }));
  if (!places && !state.suggestion) {
    const next = open[0];
    outlineOnCameras(next ? next.outline_px : null, next ? `starting pose ${state.starting.indexOf(next) + 1}` : "");
  }
}

async function captureStarting() {
  clear("starting-feedback");
  let n = 0;
  for (;;) {
    const open = state.starting.filter((p) => !p.captured_by);
    if (!open.length) break;
    const p = open[0];
    const i = state.starting.indexOf(p);
    const last = open.length === 1;
    const ok = await captureAt(p.screen_pose, `Starting pose ${i + 1} of ${state.starting.length}`,
                               "starting-feedback", last);
    if (!ok) return;
    n += 1;
    if (state.starting.filter((q) => !q.captured_by).length >= open.length) {
      tell("starting-feedback", "warn", `Starting pose ${i + 1} was captured but does not ` +
           "match its placement; look at its maps, then capture the rest one by one.");
      return;
    }
  }
  tell("starting-feedback", "ok", `${n} starting poses captured. Next: follow the suggested ` +
       "next pose, or calibrate.");
}

async function loadVariety() {
  const box = $("#variety");
  let v;
  try {
    v = await api("GET", `/sessions/${state.session.id}/pose-variety`);
  } catch (e) {
    state.variety = null;
    box.replaceChildren(el("p", { class: "warn" }, explain(e)));
    return;
  }
  state.variety = v;
  const items = v.duplicates.map((d) => {
    const p = state.poses.find((q) => q.id === d.pose_id);
    return el("li", { class: "warn", "data-duplicate": d.pose_id },
      `Pose ${p ? p.index : d.pose_id} repeats pose ${poseName(d.repeats)} (${(100 * d.similarity).toFixed(0)}% alike): ` +
      "it adds almost nothing. Move or tilt the screen and capture again; delete the repeat. ",
      p ? el("button", { class: "danger", onclick: act("poses-feedback", () => deletePose(p)) }, "delete it") : null);
  });
  const models = Object.entries(v.ready_for_calibration || {});
  box.replaceChildren(
    el("h4", {}, "Pose variety"),
    el("p", { class: v.ready_for_guidance && !items.length ? "ok" : "warn" }, v.reason),
    items.length ? el("ul", {}, ...items) : "",
    models.length ? el("p", { class: "explain" }, "Enough varied poses for: ",
      ...models.map(([m, ok]) => el("span", { class: ok ? "ok tag" : "bad tag", title: ok ? "ready" : "needs more varied poses" }, `${m} ${ok ? "yes" : "not yet"}`))) : "");
}

// --- the suggested next pose ---------------------------------------------------------------
async function loadNextPose() {
  const text = $("#next-pose-text");
  const img = $("#next-pose-img");
  const chosen = $("#calibrate-model").value;
  const model = ["opencv5", "opencv-rational", "fisheye"].includes(chosen) ? chosen : "opencv-rational";
  const asked = ++state.nextPoseAsked;  // only the newest answer is shown
  try {
    const g = await api("GET", `/sessions/${state.session.id}/next-pose?model=${model}`);
    if (asked !== state.nextPoseAsked) return;
    state.suggestion = g;
    if (g.cameras) {  // a rig: which cameras the pose serves, and where each sees the screen
      text.replaceChildren(...rigNextPose(g));
      img.hidden = true;
      for (const c of g.cameras) state.cameras.get(c.camera)?.setOutline(c.outline_px || null, "suggested next pose");
      return;
    }
    const p = g.predicted_worst_ray_sigma_urad;
    const [u, v] = g.screen_center_px;
    const where = g.placement ||
      `${g.distance_mm.toFixed(0)} mm from the camera, tilted ${g.tilt_deg.toFixed(0)} deg towards ` +
      `${g.tilt_azimuth_deg.toFixed(0)} deg, its centre at pixel (${u.toFixed(0)}, ${v.toFixed(0)}), ` +
      `filling ${(100 * g.image_fraction).toFixed(0)}% of the image`;
    text.replaceChildren(
      g.helps === false
        ? el("p", { class: "ok" }, g.advice || "No further pose would lower the uncertainty much: calibrate.")
        : el("p", {}, `Place the screen ${where}.`, g.advice ? el("span", { class: "explain" }, ` ${g.advice}`) : ""),
      // The service's default lets a next pose reach past the image's edge: say it is meant.
      g.helps !== false && g.screen_visible_fraction < 1
        ? el("p", { class: "explain", id: "next-pose-visible" },
          `About ${(100 * g.screen_visible_fraction).toFixed(0)} % of the screen is in view there; ` +
          "the rest reaching past the image's edge is intended: every pixel that sees the screen " +
          "is measured, and this puts data into the image's corners.")
        : "",
      el("p", { class: "explain", title: "ray sigma: the 1-sigma uncertainty of the viewing direction of a pixel, in microradians (1 urad is 1 um at 1 m)" },
        `Worst predicted ray sigma (${g.model}, from ${g.poses_used.length} poses): ` +
        `${fmt(p.now, 3)} urad now, ${fmt(p.after, 3)} urad after this pose. Smaller is better.`));
    // The image's URL changes with its content; older services answer one URL per model.
    img.src = /[?&]key=/.test(g.image) ? g.image : `${g.image}&poses=${g.poses_used.length}-${g.poses_used.at(-1)}`;
    img.hidden = false;
    if (g.outline_px) outlineOnCameras(g.outline_px, "suggested next pose");
  } catch (e) {
    if (asked !== state.nextPoseAsked) return;
    state.suggestion = null;
    img.hidden = true;
    text.textContent = explain(e);
  }
}

// --- calibrations, downloads and comparison ------------------------------------------------
async function loadCalibrations() {
  state.calibrations = await api("GET", `/calibrations?session_id=${state.session.id}`);
  $("#calibrations tbody").replaceChildren(...state.calibrations.map((c) => {
    const ok = c.status === "succeeded";
    return el("tr", { "data-calibration": c.id, class: state.calibration === c.id ? "current" : null },
      el("td", {}, c.id), el("td", {}, c.model),
      el("td", { class: ok ? "" : "bad" }, c.status + (c.error ? `: ${c.error}` : "")),
      el("td", {}, fmt(c.stats && c.stats.rms_px)), el("td", {}, fmt(c.stats && c.stats.noise_floor_ratio, 3)),
      el("td", {}, ok ? el("a", { href: `/calibrations/${c.id}/report.html`, target: "_blank", class: "report-link" }, "report") : "-"),
      el("td", {}, ok ? el("button", { class: "open-cal", onclick: act("calibrations-feedback", () => selectCalibration(c.id)) }, "downloads, compare") : "-"),
      el("td", {}, el("button", { class: "danger", "aria-label": `delete calibration ${c.id}`,
                                  onclick: act("calibrations-feedback", () => deleteCalibration(c)) }, "delete")));
  }));
  const wanted = state.calibration || urlState().calibration;
  if (wanted && state.calibrations.some((c) => c.id === wanted && c.status === "succeeded")) selectCalibration(wanted);
  else if (state.calibration) { state.calibration = null; $("#calibration-detail").hidden = true; setUrl({ calibration: null }); }
}

async function calibrate(ev) {
  ev.preventDefault();
  clear("calibrate-feedback");
  const rig = rigCameraNames();
  const body = rig ? rigCalibrationBody($("#rig-models"), [...state.heldout]) : { model: $("#calibrate-model").value };
  const model = rig ? `rig (${Object.entries(body.camera_models).map(([c, m]) => `${c}: ${m}`).join(", ")})` : body.model;
  if (!rig && state.heldout.size) body.heldout_pose_ids = [...state.heldout];
  const job = await api("POST", `/sessions/${state.session.id}/${rig ? "rig-calibrations" : "calibrations"}`, body);
  tell("calibrate-feedback", "info", `Calibrating with ${model} (${job.id}).`);
  await loadCalibrations();
  const end = await follow(job, PANELS.calibrate, `Calibrate ${model}`);
  await loadCalibrations();
  if (end.status !== "succeeded") { tell("calibrate-feedback", "error", explainJob(end)); return; }
  const cal = end.resource.split("/").pop();
  const rec = state.calibrations.find((c) => c.id === cal);
  tell("calibrate-feedback", "ok", `Calibration ${cal} succeeded` +
       (rec && rec.stats && rec.stats.rms_px != null ? `: RMS ${fmt(rec.stats.rms_px, 3)} px` : "") +
       ". Its report and model files are below.");
  selectCalibration(cal);
}

// --- the closed loop on a rig with a mover ---------------------------------------------------
async function loadAutoLog() {
  if (!hasMover(state.rig)) return;
  try {
    $("#auto-log").replaceChildren(...autoLog(await api("GET", `/sessions/${state.session.id}/auto`)));
  } catch (e) {
    if (!(e instanceof ServiceError && e.status === 404)) throw e;  // no run yet
  }
}

async function runAuto(ev) {
  ev.preventDefault();
  clear("auto-feedback");
  const job = await api("POST", `/sessions/${state.session.id}/auto`, autoBody($("#auto-form")));
  tell("auto-feedback", "info", `Running (${job.id}): the robot moves, then each pose is captured.`);
  const timer = setInterval(() => loadAutoLog().catch(() => {}), 2000);
  let end;
  try { end = await follow(job, PANELS.auto, "Automatic run"); } finally { clearInterval(timer); }
  await Promise.all([loadAutoLog(), refreshSession()]);
  if (end.status !== "succeeded") { tell("auto-feedback", "error", explainJob(end)); return; }
  tell("auto-feedback", "ok", "The run ended: its poses are in the table; calibrate them below.");
}

async function deleteCalibration(c) {
  if (!confirm(`Delete calibration ${c.id} (${c.model}) and its files?`)) return;
  await api("DELETE", `/calibrations/${c.id}`);
  tell("calibrations-feedback", "ok", `Calibration ${c.id} deleted.`);
  await loadCalibrations();
}

function downloadLink(path, label, title) {
  const a = el("a", { href: path, class: "download", title }, label);
  a.onclick = act("downloads-feedback", async (ev) => {
    ev.preventDefault();
    await saveFile(a.getAttribute("href"), label);
  });
  return a;
}

// Fetch with the token and save; a refusal is explained instead of saved as a file.
async function saveFile(path, label) {
  tell("downloads-feedback", "info", `Preparing ${label}...`);
  const r = await request("GET", path);
  const disposition = r.headers.get("Content-Disposition") || "";
  const named = /filename="?([^";]+)"?/.exec(disposition);
  const name = named ? named[1] : `${state.calibration}-${path.split("?")[0].split("/").pop()}`;
  const info = r.headers.get("Phasecal-Export-Info");
  const blob = await r.blob();
  const url = URL.createObjectURL(blob);
  const a = el("a", { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60000);
  let note = "";
  if (info) {
    const i = JSON.parse(info);
    note = i.exact === false && i.residual ? ` (an approximation: ${JSON.stringify(i.residual)})` : i.exact ? " (exact)" : "";
  }
  tell("downloads-feedback", "ok", `Saved ${name}${note}.`);
}

function exportPath(cal, format) {
  const q = new URLSearchParams({ format });
  const pinhole = $("#remap-pinhole").value.trim();
  if (format === "remap" && pinhole) q.set("pinhole", pinhole);
  if (format === "mrcal" && $("#mrcal-approximate").checked) q.set("approximate", "true");
  return `/calibrations/${cal}/export?${q}`;
}

function selectCalibration(cal) {
  state.calibration = cal;
  setUrl({ calibration: cal });
  const rec = state.calibrations.find((c) => c.id === cal);
  for (const tr of document.querySelectorAll("#calibrations tbody tr")) tr.classList.toggle("current", tr.dataset.calibration === cal);
  $("#calibration-detail").hidden = false;
  $("#calibration-title").textContent = `Calibration ${cal}${rec ? ` (${rec.model})` : ""}`;
  const renderDownloads = () => $("#downloads").replaceChildren(
    el("li", {}, downloadLink(`/calibrations/${cal}/files/model.json`, "model.json", "phasecal's own model file: every tool of phasecal reads it")),
    ...EXPORT_FORMATS.map(([f, label, what]) => el("li", { "data-format": f },
      downloadLink(exportPath(cal, f), label, what), el("span", { class: "explain" }, ` ${what}`))),
    el("li", {}, el("a", { href: `/calibrations/${cal}/report.html`, target: "_blank" }, "open the report"),
      el("span", { class: "explain" }, " numbers, residuals per pose, uncertainty; "),
      downloadLink(`/calibrations/${cal}/report.html?download=1`, "save the report as one file", "one HTML file with its pictures inside")));
  const rig = rec && isRigCalibration(rec);
  $("#rig-result").replaceChildren();
  for (const id of ["#single-downloads", "#compare-box"]) $(id).style.display = rig ? "none" : "";
  if (rig) {
    showRig(cal).catch((e) => tell("downloads-feedback", "error", explain(e), e));
    return;
  }
  renderDownloads();
  $("#remap-pinhole").oninput = renderDownloads;
  $("#mrcal-approximate").onchange = renderDownloads;
  const others = state.calibrations.filter((c) => c.status === "succeeded" && c.id !== cal);
  $("#compare-with").replaceChildren(...others.map((c) => el("option", { value: c.id }, `${c.id} (${c.model})`)));
  $("#compare-btn").disabled = others.length === 0;
  $("#compare-result").textContent = others.length ? "" : "calibrate again (another model or poses) to compare";
  clear("compare-feedback");
}

// A rig calibration: the extrinsics with their sigma and every rig download.
async function showRig(cal) {
  const rig = await api("GET", `/calibrations/${cal}/rig`);
  $("#rig-result").replaceChildren(
    el("h4", {}, `Extrinsics in ${rig.reference}'s frame`), rigResult(rig),
    el("p", { class: "explain" }, "1-sigma from each camera's covariance: translation in mm, rotation in mrad."));
  $("#downloads").replaceChildren(
    ...rigDownloads(cal, rig).map(([path, label, what]) => el("li", { "data-rig-download": label },
      downloadLink(path, label, what), el("span", { class: "explain" }, ` ${what}`))),
    el("li", {}, el("a", { href: `/calibrations/${cal}/report.html`, target: "_blank" }, "open the report"),
      el("span", { class: "explain" }, " every camera, the extrinsics with sigma, the verdict")));
}

async function compare() {
  const a = state.calibration, b = $("#compare-with").value;
  tell("compare-feedback", "info", `Comparing ${a} with ${b}...`);
  const d = await api("GET", `/calibrations/${a}/diff/${b}`);
  const page = d.page || d.image;
  $("#compare-result").replaceChildren(
    `Viewing directions differ by ${fmt(d.rms_urad, 3)} urad RMS, ${fmt(d.p95_urad, 3)} urad ` +
    `at the 95th percentile, ${fmt(d.max_urad, 3)} urad at most, after the best rotation. `,
    el("a", { href: page, target: "_blank", class: "diff-link" }, d.page ? "open the comparison" : "difference map"));
  clear("compare-feedback");
}

// --- wiring ---------------------------------------------------------------------------------
async function start() {
  $("#token").value = token();
  if (token()) setToken(token());
  await loadRigs();
  await loadSessions();
  const wanted = urlState().session;
  if (wanted) await openSession(wanted);
  say("ready");
}

function guarded(fn) {
  return async (...args) => {
    try { await fn(...args); } catch (e) { say(explain(e), true); }
  };
}

$("#token-form").onsubmit = guarded(async (ev) => { ev.preventDefault(); setToken($("#token").value); await start(); });
$("#new-session-rig").onchange = showSimHint;
$("#new-session").onsubmit = act("new-session-feedback", async (ev) => {
  ev.preventDefault();
  clear("new-session-feedback");
  const s = await api("POST", "/sessions", { name: $("#new-session-name").value,
    rig_id: $("#new-session-rig").value || null, preset: $("#new-session-preset").value });
  await openSession(s.id);
});
$("#capture-btn").onclick = act("capture-feedback", captureClicked);
$("#cancel-btn").onclick = act("capture-feedback", cancel);
$("#cal-cancel-btn").onclick = act("calibrate-feedback", cancel);
$("#starting-btn").onclick = act("starting-feedback", captureStarting);
$("#calibrate-form").onsubmit = act("calibrate-feedback", calibrate);
$("#auto-form").onsubmit = act("auto-feedback", runAuto);
$("#auto-cancel-btn").onclick = act("auto-feedback", cancel);
$("#calibrate-model").onchange = act("calibrate-feedback", async () => { if (state.session) await loadNextPose(); });
$("#compare-btn").onclick = act("compare-feedback", compare);
window.addEventListener("resize", () => { for (const v of state.cameras.values()) v.draw(); });
guarded(start)();
