"""Pure numerics: decoding, camera models, fitting, evaluation; no hardware, no HTTP.

The library's front door: the service (`api`), the CLI and the benchmarks take the numerics
from here (`from calibration import decode_frames, load_model, ...`), so the modules behind
it can move without touching them. What every layer shares, the file formats and the job
plumbing (plan, maps, frame store, atomic writer, progress), is `calibration.shared`, and
is imported directly, as are `calibration.extras`, `calibration.prefault` and
`calibration.readahead`.

Names load lazily (PEP 562): a command that needs one function does not import the
decoder's kernels or matplotlib with it.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    # decode: frames of one pose -> per-pixel screen points with uncertainty
    "DecodeError": "decode",
    "DecodeOptions": "decode",
    "StreamingDecoder": "decode",
    "read_frames": "decode",
    "decode_frames": "pipeline",
    "COMPILED_MIN_PIXELS": "decode.decoder",
    "warm_up": "decode.kernel_warm",
    "retain_freed_memory": "decode.heap",
    "one_heap_arena": "decode.heap",
    "warm_heap": "decode.heap",
    "holds_pixels": "decode.sums_cache",
    # fit through the registry
    "MODELS": "fit.registry",
    "MODEL_NAMES": "fit.registry",
    "PARAMETRIC": "fit.registry",
    "model_spec": "fit.registry",
    "DegenerateError": "fit.ransac",
    "calibrate_files": "pipeline",
    "write_model_folder": "pipeline",
    # passive targets: boards and surveyed points -> observations -> a model
    "TargetSpec": "targets.board",
    "TargetSpecError": "targets.board",
    "detect_file": "targets.detect",
    "detect_image": "targets.detect",
    "ObservationOptions": "fit.sparse.options",
    "ObservationFitError": "fit.sparse.fit",
    "calibrate_observations": "fit.sparse.calibrate",
    "observation_refusal": "fit.sparse.calibrate",
    "calibrate_observation_files": "pipeline",
    "write_uncertainty_png": "fit.sparse.figure",
    # hand-eye: robot poses and the camera's views -> the camera on (or beside) the robot
    "HANDEYE_FORMAT": "handeye.solve",
    "MOUNTS": "handeye.solve",
    "MIN_HANDEYE_VIEWS": "handeye.solve",
    "handeye_files": "handeye.pipeline",
    "handeye_from_maps": "handeye.pipeline",
    "ROBOT_POSES_FORMAT": "handeye.robot_poses",
    "RobotPoses": "handeye.robot_poses",
    "RobotPosesError": "handeye.robot_poses",
    "robot_poses_from_dict": "handeye.robot_poses",
    "intrinsics_from_images": "fit.classic.quick",
    "intrinsics_from_maps": "fit.classic.quick",
    "read_white_flat": "fit.classic.quick",
    "white_flat_index": "fit.classic.quick",
    # models
    "CameraModel": "models.base",
    "ModelError": "models.base",
    "load_model": "models.base",
    "save_model": "models.base",
    "OpenCV5Model": "models.parametric",
    # rigs: several cameras fitted jointly, their extrinsics with covariance
    "RigInput": "fit.rig.inputs",
    "RigOptions": "fit.rig.options",
    "split_rig_options": "fit.rig.options",
    "RigResult": "fit.rig.result",
    "calibrate_rig": "fit.rig.calibrate",
    "calibrate_rig_files": "fit.rig.files",
    "check_connected": "fit.rig.graph",
    "RigModel": "shared.rig_model",
    "RigCamera": "shared.rig_model",
    "RigModelError": "shared.rig_model",
    "load_rig": "shared.rig_model",
    "save_rig": "shared.rig_model",
    "rig_from_dict": "shared.rig_model",
    "is_rig_document": "shared.rig_model",
    "RIG_FORMATS": "rig_export",
    "RIG_FILE_NAMES": "rig_export",
    "RIG_MEDIA_TYPES": "rig_export",
    "rig_export_bytes": "rig_export",
    "export_rig": "rig_export",
    "stereo_rectify": "undistort",
    # evaluate and guide
    "plan_next_pose": "guidance",
    "plan_rig_next_pose": "guidance_rig",
    "RigSuggestion": "guidance_rig",
    "plan_step": "auto_plan",
    "starting_moves": "auto_plan",
    "screen_distance_mm": "auto_plan",
    "START_TURNS": "auto_plan",
    "START_STEP_MM": "auto_plan",
    "probe_moves": "auto_plan",
    "covers_screen": "auto_plan",
    "MIN_SCREEN_COVERAGE": "auto_plan",
    "session_points": "guidance",
    "DEFAULT_MIN_VISIBLE": "guidance_placement",
    "NominalCamera": "guidance_start",
    "nominal_camera": "guidance_start",
    "starting_poses": "guidance_start",
    "ObservedPose": "guidance_variety",
    "observe": "guidance_variety",
    "pose_variety": "guidance_variety",
    "captured_by": "guidance_variety",
    "ray_sigma_map": "uncertainty",
    "worst_ray_sigma": "uncertainty",
    # export
    "ExportOptions": "formats",
    "FILE_NAMES": "formats",
    "MEDIA_TYPES": "formats",
    "export_bytes": "formats",
    "export_model": "formats",
    "load_model_any": "formats",
    "parse_pinhole": "formats",
    "parse_rotation": "formats",
    "undistort_pixels": "formats",
    "export_opencv_yaml": "export",
    "export_ros_yaml": "export",
    # reports and figures
    "gather": "report_data",
    "ReportHeader": "report_data",
    "write_report": "report_html",
    "self_contained": "report_html",
    "with_links": "report_html",
    "is_current": "report_html",
    "write_diff": "report_diff",
    "ReportInputs": "report_draw",
    "DiffInputs": "report_draw",
    "FitFiles": "report_draw",
    "draw_report": "report_draw",
    "draw_diff": "report_draw",
    "RigReportInputs": "report_rig",
    "draw_rig_report": "report_rig",
    "rig_downloads": "report_rig",
    "rig_model_stats": "report_rig",
    "write_rig_downloads": "report_rig",
    "served_downloads": "report_downloads",
    "write_downloads": "report_downloads",
    "write_residual_report": "report",
    "count_png": "report_plots",
    "guidance_png": "guidance_plot",
    "rig_camera_guidance_png": "guidance_plot",
    "rig_sigma_range": "guidance_plot",
    "one_at_a_time": "figures",
    "subplots": "figures",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Load a public name from its module on first use (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'calibration' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"calibration.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
