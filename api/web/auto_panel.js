// The closed loop on a rig with a mover: the run's settings, and its log as it grows (each
// pose taken or skipped, the worst predicted ray sigma after it, why it stopped, the hand-eye).

import { el, fmt } from "/ui/dom.js";

// Whether the rig record's config names a mover (the loop needs one).
export function hasMover(rig) { return !!(rig && rig.config && rig.config.mover); }

// The body of POST /sessions/{id}/auto from the form.
export function autoBody(form) {
  return {
    target: { worst_ray_sigma_urad: Number(form.querySelector("#auto-target").value) },
    budget: Number(form.querySelector("#auto-budget").value),
    mount: form.querySelector("#auto-mount").value,
    model: "opencv5",
  };
}

function place(entry) {
  const t = entry.flange && entry.flange.t_mm;
  return t ? `flange at (${t.map((v) => fmt(v, 3)).join(", ")}) mm` : "";
}

// The run's log as list items, the newest last; a summary line first.
export function autoLog(log) {
  const items = log.poses.map((p, i) => el("li", { "data-pose": p.pose_id },
    `pose ${i + 1}: ${p.reason || ""} ${place(p)}` +
    (p.worst_ray_sigma_urad != null ? `; worst ray sigma then ${fmt(p.worst_ray_sigma_urad, 3)} urad` : "")));
  for (const s of log.skipped || []) {
    items.push(el("li", { class: "explain" }, `skipped: ${s.why || s.reason || ""} ${place(s)}`));
  }
  if (log.moving_to) items.push(el("li", { class: "explain" }, `moving: ${log.moving_to.reason || ""} ${place(log.moving_to)}`));
  const he = log.handeye && log.handeye.sigma;
  const summary = [
    log.worst_ray_sigma_urad != null ? `worst ray sigma ${fmt(log.worst_ray_sigma_urad, 3)} urad` : "no fit yet",
    he ? `hand-eye 1-sigma ${fmt(he.translation_mm, 2)} mm, ${fmt(he.rotation_mrad, 2)} mrad` : null,
    log.stop_reason ? `stopped: ${log.stop_reason}` : "running",
  ].filter(Boolean).join("; ");
  return [el("li", { class: "auto-summary" }, summary), ...items];
}
