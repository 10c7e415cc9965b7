"""Exports of a calibration in any format (`GET .../export?format=F`) and undistort-points."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response
from pydantic import BaseModel, Field

from api.problems import Problem
from api.routes.calibrations import fitted_model
from api.routes.common import PROBLEM_RESPONSES
from api.routes.points import json_rows, point_rows
from api.schemas import MAX_ID_LENGTH, MAX_POINTS, Coord, Num, strict_config
from api.services import Services, get_services
from calibration import (
    FILE_NAMES,
    MEDIA_TYPES,
    ExportOptions,
    ModelError,
    export_bytes,
    parse_pinhole,
    parse_rotation,
    undistort_pixels,
)

router = APIRouter(tags=["calibrations"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
Format = Literal["opencv-yaml", "ros", "mrcal", "remap", "opencv-fit"]
INFO_HEADER = "Phasecal-Export-Info"


def _options(svc: Services, *, pinhole: str | None, rotation: str | None, align_to: str | None,
             **rest: Any) -> ExportOptions:
    """ExportOptions from query/body values; malformed values are 422 problems."""
    try:
        return ExportOptions(
            pinhole=parse_pinhole(pinhole) if pinhole else None,
            rotation=parse_rotation(rotation) if rotation else None,
            align_to=fitted_model(svc, align_to) if align_to else None, **rest)
    except ModelError as exc:
        raise Problem(422, "validation-error", str(exc)) from None


@router.get("/calibrations/{cal_id}/export", response_class=Response,
            responses={200: {"content": {"application/x-yaml": {}, "text/plain": {},
                                         "application/octet-stream": {}},
                             "description": f"the file; {INFO_HEADER}: JSON (exact, residual)"}})
def export(
    cal_id: str, svc: Svc, format: Format,
    pinhole: Annotated[str | None, Query(description="remap: FX,FY,CX,CY,W,H")] = None,
    rotation: Annotated[str | None, Query(description="remap: RX,RY,RZ or 9 numbers")] = None,
    align_to: Annotated[str | None, Query(description="remap: calibration id whose frame the "
                                                      "virtual camera uses")] = None,
    camera_name: Annotated[str, Query(description="ros: camera_name")] = "camera",
    approximate: Annotated[bool, Query(description="mrcal: spline fit of a fisheye")] = False,
    spline_nx: Annotated[int, Query(ge=4, le=100, description="mrcal spline knots")] = 16,
    opencv_kind: Literal["opencv5", "opencv-rational"] = "opencv-rational",
) -> Response:
    """The calibration's model as opencv-yaml, ros, mrcal, remap (NPZ) or opencv-fit (NPZ).

    A model the format cannot carry exactly is refused (422 `export-refused`, the reason in
    `detail`); approximations (mrcal spline of a generic model, opencv-fit) report their
    residual in the `Phasecal-Export-Info` header.
    """
    model = fitted_model(svc, cal_id)
    opts = _options(svc, pinhole=pinhole, rotation=rotation, align_to=align_to,
                    camera_name=camera_name, approximate=approximate, spline_nx=spline_nx,
                    opencv_kind=opencv_kind)
    try:
        data, info = export_bytes(model, format, opts)
    except ModelError as exc:
        raise Problem(422, "export-refused", f"format {format}: {exc}") from None
    name = f"{cal_id}-{FILE_NAMES[format]}"
    return Response(data, media_type=MEDIA_TYPES[format], headers={
        "Content-Disposition": f'attachment; filename="{name}"',
        INFO_HEADER: json.dumps(info, separators=(",", ":"))})


class UndistortRequest(BaseModel):
    """Model pixels and the virtual pinhole they are mapped to (default: the model's K)."""

    model_config = strict_config({"pixels": [[320.0, 240.0]],
                                  "pinhole": [400.0, 400.0, 320.0, 240.0]})
    # fail_fast: one error for a bad row, not one per row (200,000 errors need ~300 MB)
    pixels: list[tuple[Coord, Coord]] = Field(max_length=MAX_POINTS, fail_fast=True)
    pinhole: tuple[Num, Num, Num, Num] | None = Field(
        None, description="FX, FY, CX, CY of the virtual pinhole")
    rotation: list[Num] | None = Field(None, max_length=9,
                                       description="3 (Rodrigues) or 9 numbers")
    align_to: str | None = Field(None, max_length=MAX_ID_LENGTH,
                                 description="calibration id whose frame to use")


class UndistortResponse(BaseModel):
    """Virtual-pinhole pixels; null rows where a ray does not point in front of it."""

    pixels: list[list[float | None]]



@router.post("/calibrations/{cal_id}/undistort-points", response_model=UndistortResponse)
def undistort_points(cal_id: str, body: UndistortRequest, svc: Svc) -> dict[str, Any]:
    """Pixels of the model -> pixels of a virtual pinhole (cv2.undistortPoints with R, P)."""
    model = fitted_model(svc, cal_id)
    pin = None if body.pinhole is None else ",".join(map(str, (*body.pinhole, 1, 1)))
    rot = None if body.rotation is None else ",".join(map(str, body.rotation))
    opts = _options(svc, pinhole=pin, rotation=rot, align_to=body.align_to)
    try:
        out = undistort_pixels(model, point_rows(body.pixels, 2), opts)
    except ModelError as exc:
        raise Problem(422, "validation-error", str(exc)) from None
    return {"pixels": json_rows(out)}

