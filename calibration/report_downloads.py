"""What a report offers for download: the model itself and each export format the model can
be written in, with a note saying whether the export is exact, approximate or why it is not
offered. A served report links the service's export route; `phasecal report` writes the
files beside the page."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.formats import FILE_NAMES, FORMATS, ExportOptions, export_bytes
from calibration.models.base import CameraModel, ModelError
from calibration.models.parametric import FisheyeModel, OpenCVRationalModel, PinholeFamily
from calibration.report_data import Download

_LABELS = {"opencv-yaml": "OpenCV YAML (cv2.FileStorage)", "ros": "ROS camera_info YAML",
           "mrcal": "mrcal .cameramodel", "remap": "remap tables for cv2.remap (NPZ)",
           "opencv-fit": "best-fitting OpenCV model and its residual map (NPZ)"}


@dataclass
class ExportOffer:
    """One export format for one model: its query options, or why it is not offered."""

    fmt: str
    label: str
    options: dict[str, str]  # query parameters the export needs (e.g. approximate=true)
    note: str
    available: bool


def export_offers(model: CameraModel) -> list[ExportOffer]:
    """Every export format with what this model gives in it (decided from the model's type
    and terms, without computing the export)."""
    pinhole = isinstance(model, PinholeFamily)
    out = []
    for fmt in FORMATS:
        label, options, note, ok = _LABELS[fmt], {}, "exact", True
        if fmt in ("opencv-yaml", "ros") and not pinhole:
            ok, note = False, f"a {model.type_name} model has no camera matrix and distortion form"
        elif (fmt == "ros" and isinstance(model, OpenCVRationalModel)
              and np.any(model.dist[8:] != 0)):
            ok, note = False, "the thin-prism terms s1..s4 have no ROS distortion model"
        elif fmt == "mrcal" and isinstance(model, FisheyeModel):
            options, note = {"approximate": "true"}, "spline approximation (residual in the file)"
        elif fmt == "mrcal" and not pinhole:
            note = "spline approximation (residual in the file)"
        elif fmt == "remap" and not pinhole:
            ok, note = False, ("needs a virtual pinhole: ask the export route with "
                               "pinhole=FX,FY,CX,CY,W,H")
        elif fmt == "remap":
            note = "maps into a pinhole with the model's own camera matrix"
        elif fmt == "opencv-fit":
            note = "approximation; its residual is stored with it"
        out.append(ExportOffer(fmt, label, options, note, ok))
    return out


def served_downloads(model: CameraModel, cal_id: str) -> list[Download]:
    """The model and its exports as links to the service's routes."""
    out = [Download("model (phasecal JSON)", f"/calibrations/{cal_id}/files/model.json",
                    "the fitted model with its covariance")]
    for offer in export_offers(model):
        query = "".join(f"&{k}={v}" for k, v in offer.options.items())
        href = f"/calibrations/{cal_id}/export?format={offer.fmt}{query}"
        out.append(Download(offer.label, href if offer.available else None, offer.note))
    return out


def write_downloads(model: CameraModel, model_json: Path, out_dir: Path) -> list[Download]:
    """Write the model and each export this model has into `out_dir`, linked by file name."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "model.json").write_bytes(model_json.read_bytes())
    out = [Download("model (phasecal JSON)", "model.json", "the fitted model")]
    for offer in export_offers(model):
        if not offer.available:
            out.append(Download(offer.label, None, offer.note))
            continue
        opts = ExportOptions(approximate=offer.options.get("approximate") == "true")
        try:
            data, _ = export_bytes(model, offer.fmt, opts)
        except ModelError as exc:
            out.append(Download(offer.label, None, str(exc)))
            continue
        (out_dir / FILE_NAMES[offer.fmt]).write_bytes(data)
        out.append(Download(offer.label, FILE_NAMES[offer.fmt], offer.note))
    return out


__all__ = ["ExportOffer", "export_offers", "served_downloads", "write_downloads"]
