// A session on a rig of several cameras: each camera's part of a pose, its maps, a model per
// camera for "Calibrate rig", the next pose's cameras, and the rig result (extrinsics with
// their 1-sigma) with the rig model's downloads.

import { el, fmt } from "/ui/dom.js";

const RIG_MODELS = ["opencv5", "opencv-rational", "fisheye", "sgcc", "raygrid"];
const CAMERA_FORMATS = [       // single-camera exports of one camera of a rig
  ["opencv-yaml", "OpenCV YAML"], ["ros", "ROS camera_info"], ["mrcal", "mrcal .cameramodel"],
];

// Whether a calibration record is of a rig (it stores a rig model).
export function isRigCalibration(c) { return (c.exports || []).includes("rig.json"); }

// One line per camera of a several-camera pose: its status and valid pixels.
export function poseCameraCell(p) {
  if (!p.cameras) return p.valid_pixels ?? "-";
  return el("div", { class: "rig-cameras" }, ...p.cameras.map((c) => el("div", {
    class: `rig-camera ${["ready"].includes(c.status) ? "" : "bad"}`, "data-camera": c.name },
    `${c.name}: ${c.status}${c.valid_pixels ? `, ${c.valid_pixels} px` : ""}`)));
}

// Each camera's decoded maps of a pose, one row per camera.
export function rigMaps(base, pose) {
  return pose.cameras.map((c) => el("div", { class: "rig-maps", "data-camera": c.name },
    el("h5", {}, `camera ${c.name}`),
    ...["x", "y", "sigma", "mask"].map((k) => el("img", {
      src: `${base}/${k}.png?camera=${encodeURIComponent(c.name)}`, alt: `${k} map of ${c.name}` }))));
}

// A model chooser per camera; `fallback` is the page's model for cameras not changed.
export function modelChoosers(cameras, fallback) {
  return cameras.map((name) => {
    const sel = el("select", { id: `rig-model-${name}`, "data-camera": name,
                               "aria-label": `model of camera ${name}` },
      ...RIG_MODELS.map((m) => el("option", { value: m }, m)));
    sel.value = RIG_MODELS.includes(fallback) ? fallback : "opencv5";
    return el("label", { class: "rig-model" }, `${name} `, sel);
  });
}

// The body of POST /sessions/{id}/rig-calibrations from the choosers.
export function rigCalibrationBody(box, heldout) {
  const models = {};
  for (const sel of box.querySelectorAll("select[data-camera]")) models[sel.dataset.camera] = sel.value;
  const first = Object.values(models)[0] || "opencv5";
  const body = { model: first, camera_models: models };
  if (heldout.length) body.heldout_pose_ids = heldout;
  return body;
}

// The next pose on a rig: which cameras it serves, each camera's sigma now/after beside its
// picture (its ray sigma now with the suggested screen where that camera sees it).
export function rigNextPose(g) {
  const rows = g.cameras.map((c) => {
    const s = c.predicted_worst_ray_sigma_urad;
    const words = `${c.camera}: ${c.serves ? "sees it" : "does not see it"}; worst ray sigma ` +
      `${fmt(s.now, 3)} urad now, ${fmt(s.after, 3)} after` +
      (c.serves ? " (the dashed outline on its preview shows where)" : "");
    return el("li", { "data-camera": c.camera, class: `row ${c.serves ? "" : "explain"}` },
      el("span", { class: "col" }, words),
      c.image ? el("img", { src: c.image, style: "max-width: min(420px, 100%)",
                            alt: `predicted ray uncertainty of camera ${c.camera} now` +
                                 (c.serves ? ", with the suggested screen" : "") }) : null);
  });
  const shared = g.shared_views.map((p) => `${p.cameras.join("+")}: ${p.views}`).join(", ");
  return [
    el("p", { class: g.helps === false ? "ok" : "" }, g.advice),
    el("p", { id: "next-pose-serves" }, `Serves: ${g.serves.join(", ")}`),
    el("ul", { class: "rig-next" }, ...rows),
    el("p", { class: "explain", title: "views two cameras saw together tie their relative pose" },
       `Views shared by camera pairs: ${shared}` +
       (g.weakly_tied.length ? `; weakly tied: ${g.weakly_tied.join(", ")}` : "")),
  ];
}

// The rig result: each camera's extrinsics with 1-sigma, from GET /calibrations/{id}/rig.
export function rigResult(rig) {
  const rows = Object.entries(rig.cameras).map(([name, cam]) => {
    const e = cam.extrinsics;
    const cov = e.covariance;
    const sd = cov.map((row, i) => Math.sqrt(Math.max(row[i], 0)));
    const rt = [0, 1, 2].map((j) => -(e.R[0][j] * e.t_mm[0] + e.R[1][j] * e.t_mm[1] + e.R[2][j] * e.t_mm[2]));
    const base = Math.hypot(...rt);
    const trace = e.R[0][0] + e.R[1][1] + e.R[2][2];
    const angle = Math.acos(Math.min(1, Math.max(-1, (trace - 1) / 2))) * 180 / Math.PI;
    const sigT = Math.hypot(sd[3], sd[4], sd[5]);
    const sigR = Math.hypot(sd[0], sd[1], sd[2]) * 1e3;
    return el("tr", { "data-camera": name },
      el("td", {}, name + (name === rig.reference ? " (reference)" : "")), el("td", {}, cam.model.type || "-"),
      el("td", {}, fmt(base, 5)), el("td", {}, fmt(angle, 4)),
      el("td", {}, name === rig.reference ? "-" : fmt(sigT, 3)),
      el("td", {}, name === rig.reference ? "-" : fmt(sigR, 3)));
  });
  return el("table", { id: "rig-extrinsics" },
    el("thead", {}, el("tr", {}, ...["camera", "model", "baseline mm", "rotation deg",
      "1-sigma mm", "1-sigma mrad"].map((h) => el("th", { scope: "col" }, h)))),
    el("tbody", {}, ...rows));
}

// (path, label, what) of every rig download: the rig model, camera pairs, each camera.
export function rigDownloads(cal, rig) {
  const base = `/calibrations/${cal}/rig`;
  const names = Object.keys(rig.cameras);
  const out = [[base, "rig.json", "the rig model: every camera's model and extrinsics with covariance"],
               [`${base}/export?format=ros-transforms`, "ROS transforms", "every camera's pose as tf2 static transforms"]];
  for (let i = 0; i < names.length; i++) {
    for (let j = i + 1; j < names.length; j++) {
      const pair = `${names[i]},${names[j]}`;
      out.push([`${base}/export?format=opencv-stereo&cameras=${pair}`, `opencv-stereo ${pair}`,
                "cv2.stereoRectify's inputs: K1, D1, K2, D2, R, T (X2 = R X1 + T, mm)"]);
      out.push([`${base}/export?format=stereo-remap&cameras=${pair}`, `stereo-remap ${pair}`,
                "rectification maps for cv2.remap (NPZ)"]);
    }
  }
  for (const name of names) {
    for (const [f, label] of CAMERA_FORMATS) {
      out.push([`${base}/export?format=${f}&camera=${encodeURIComponent(name)}`, `${name}: ${label}`, `camera ${name} alone`]);
    }
  }
  return out;
}
