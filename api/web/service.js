// The REST service as the page sees it: the token, requests, and what a refusal means for the
// person at the bench (problem+json `type` and `detail` turned into a sentence with what to do).

// --- the API token -------------------------------------------------------------------------
export function token() { return localStorage.getItem("phasecal_token") || ""; }

export function setToken(value) {
  localStorage.setItem("phasecal_token", value);
  // Images, reports and the SSE stream are loaded by URL and cannot send a header:
  // the server accepts this cookie for GET requests only.
  document.cookie = "phasecal_token=" + encodeURIComponent(value) + "; path=/; SameSite=Strict";
}

function authHeaders() { return token() ? { Authorization: "Bearer " + token() } : {}; }

// --- talking to the service, and saying what its problems mean -----------------------------
export class ServiceError extends Error {
  constructor(method, path, status, problem) {
    const detail = (problem && problem.detail) || "";
    super(`${method} ${path}: ${status} ${detail}`);
    this.status = status;
    this.slug = problem && problem.type ? String(problem.type).split("/").pop() : "";
    this.detail = detail;
    this.errors = (problem && problem.errors) || [];
  }
}

export async function request(method, path, body) {
  const headers = authHeaders();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let r;
  try {
    r = await fetch(path, { method, headers,
                            body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (e) {
    throw new ServiceError(method, path, 0, { type: "unreachable", detail: String(e) });
  }
  if (!r.ok) {
    let problem = { detail: r.statusText };
    try { problem = await r.json(); } catch (e) { /* not JSON */ }
    throw new ServiceError(method, path, r.status, problem);
  }
  return r;
}

export async function api(method, path, body) {
  const r = await request(method, path, body);
  return r.status === 204 ? null : r.json();
}

// What a refusal means for the person at the bench, and what to do about it.
export function explain(err) {
  if (!(err instanceof ServiceError)) return String(err && err.message ? err.message : err);
  const d = err.detail;
  const needs = /(\S+) needs >= (\d+) training poses, got (\d+)/.exec(d);
  if (needs) {
    return `${needs[1]} needs at least ${needs[2]} poses to fit, and ${needs[3]} are ` +
      "ready. Capture more varied poses (the starting poses, then the suggested next " +
      "poses), or choose a model that needs fewer.";
  }
  switch (err.slug) {
    case "unreachable": return "The service does not answer. Is `phasecal serve` still running?";
    case "no-poses": return "There are no ready poses to calibrate yet. Capture poses first: " +
      "the starting poses are a good beginning.";
    case "not-enough-poses": return "Guidance needs at least 3 ready, varied poses. Capture " +
      "the starting poses first.";
    case "guidance-failed": return "The poses are too alike to plan from: they see the " +
      "screen from nearly the same place. Move and tilt the screen between captures (the " +
      "starting poses show where), then ask again.";
    case "rig-busy": return "The rig is busy with a capture. Wait for it to end, then try again.";
    case "job-active": return "A job is still working on this. Wait for it to end, or cancel " +
      "it, then try again.";
    case "not-simulated": return "This rig is real hardware: the page cannot move its screen. " +
      "Place the screen by hand where the outline on the camera preview shows.";
    case "insufficient-storage": return "The disk is too full for this. Delete poses or " +
      "calibrations you no longer need, then try again.";
    case "export-refused": return "This model cannot be written in that format exactly: " +
      d.replace(/^format [^:]+: /, "") + ".";
    case "not-ready": return `Not ready yet: ${d}.`;
    case "too-many-streams": return "Too many open previews or progress streams from this " +
      "computer. Close other phasecal tabs and try again.";
    case "preview-unavailable": return "No camera frame yet: the camera is busy or in " +
      "hardware-trigger mode. Frames appear here during a capture.";
    case "not-found": return `Not found: ${d}. It may have been deleted; reload the page.`;
    case "too-large": return `Too much data in one request: ${d}.`;
    default: break;
  }
  if (err.status === 401 || err.status === 403) {
    return "The service needs its API token: enter it at the top of the page and press Use.";
  }
  if (err.status === 422) {
    const field = err.errors.length && err.errors[0].loc ? err.errors[0].loc.join(".") : "";
    return `The service refused the request${field ? ` (field ${field})` : ""}: ${d}`;
  }
  return `The service answered ${err.status}: ${d}`;
}

// What a job that ended badly means, from its state's error text.
export function explainJob(end) {
  const e = end.error || "";
  if (end.status === "cancelled") return "Cancelled. Nothing was kept from the unfinished part.";
  if (/degenerate|too similar|singular|ill.conditioned/i.test(e)) {
    return "The fit could not separate the lens from the pose: the poses are too alike. " +
      "Capture more varied poses (tilted, nearer and farther, the screen in every part of " +
      "the image) and calibrate again.";
  }
  if (/interrupted/i.test(e)) return "The server stopped during this job. Resume or start again.";
  if (/no space left/i.test(e)) return "The disk ran full. Delete what you no longer need.";
  return `The job ended ${end.status}${e ? ": " + e : ""}.`;
}

