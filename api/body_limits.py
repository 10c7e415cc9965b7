"""How large a request body each route may receive, in bytes and in parsed JSON values.

File uploads (multipart bodies on the routes that take files) may be as large as
`PHASECAL_MAX_UPLOAD_BYTES`: they are streamed to disk or read as raw bytes. Every other
body is parsed as JSON, where a few bytes become a Python object of tens of bytes, so it
gets a far smaller byte limit (`PHASECAL_MAX_JSON_BYTES`, default 4 MiB: the largest plan
the plan builder makes with every preset is 20 KB, an extreme full-control plan of 1666
frames 270 KB, a rig config under 1 KB) and a budget of values, arrays/objects and nesting
depth that `api.json_shape.JsonShape` checks before the parser runs. The point routes
(project, unproject, undistort-points) take up to `MAX_POINTS` rows of numbers, so their
budget is sized from that instead, with room for a few keys and objects but not for rows of
strings or objects (which would cost several times what rows of numbers do).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from api.json_shape import JsonShape
from api.schemas import MAX_POINTS

UPLOAD_SETTING = "PHASECAL_MAX_UPLOAD_BYTES"
JSON_SETTING = "PHASECAL_MAX_JSON_BYTES"
# Routes whose multipart bodies carry files (checked against the app's routes by the tests).
UPLOAD_ROUTES = (
    "/sessions/{session_id}/poses/import",
    "/sessions/{session_id}/poses/import-maps",
    "/target-sessions/{session_id}/views",
)
# Routes whose JSON bodies are arrays of up to MAX_POINTS rows of 2 or 3 numbers.
POINT_ROUTES = (
    "/calibrations/{cal_id}/project",
    "/calibrations/{cal_id}/unproject",
    "/calibrations/{cal_id}/undistort-points",
)
# 200,000 rows of three full-precision numbers pretty-printed (indent 2) take about 19 MB.
POINT_ROUTE_BYTES = 24 << 20
BYTES_PER_VALUE = 16  # a general JSON body may hold max_json_bytes / 16 values ...
BYTES_PER_CONTAINER = 64  # ... and max_json_bytes / 64 arrays and objects
MAX_DEPTH = 32  # a plan nests 4 deep, a rig config 3; nothing legitimate comes near


@dataclass(frozen=True)
class BodyBudget:
    """What one request's body may be: bytes, and for JSON the shape of what it parses to."""

    max_bytes: int
    why: str  # what sets max_bytes (the setting that raises it)
    json: bool  # the body is parsed as JSON, so its shape is checked
    max_values: int = 0
    max_containers: int = 0
    max_objects: int = 0
    max_strings: int = 0
    max_depth: int = MAX_DEPTH


@dataclass(frozen=True)
class Refusal:
    """Why a body is refused: an HTTP status, a problem slug and a detail naming the limit."""

    status: int
    slug: str
    detail: str


def _route_pattern(templates: tuple[str, ...]) -> re.Pattern[str]:
    """One regex matching any of the route templates (`{name}` matches one path segment)."""
    return re.compile("|".join(
        "".join("[^/]+" if part.startswith("{") else re.escape(part)
                for part in re.split(r"(\{[^}]*\})", t))
        for t in templates))


_UPLOAD_RE = _route_pattern(UPLOAD_ROUTES)
_POINT_RE = _route_pattern(POINT_ROUTES)


def is_multipart(content_type: bytes | None) -> bool:
    """True for a `multipart/form-data` content type (any parameters, any case)."""
    main = (content_type or b"").split(b";", 1)[0].strip().lower()
    return main == b"multipart/form-data"


class BodyLimits:
    """The budget of each request from the two byte settings (see the module docstring)."""

    def __init__(self, max_upload_bytes: int, max_json_bytes: int) -> None:
        self.max_upload_bytes = max_upload_bytes
        self.max_json_bytes = max_json_bytes
        self.upload = BodyBudget(max_upload_bytes, UPLOAD_SETTING, json=False)
        values = max_json_bytes // BYTES_PER_VALUE
        containers = max_json_bytes // BYTES_PER_CONTAINER
        self.general = self._json_budget(max_json_bytes, JSON_SETTING, values, containers,
                                         containers, values)
        # rows of numbers: one array and 2-3 numbers each, a few keys and objects around them
        self.points = self._json_budget(
            POINT_ROUTE_BYTES, f"room for {MAX_POINTS} points, the most these routes take",
            4 * MAX_POINTS + 1024, MAX_POINTS + 64, 16, 64)

    def _json_budget(self, max_bytes: int, why: str, values: int, containers: int,
                     objects: int, strings: int) -> BodyBudget:
        """A JSON budget, its bytes never above the upload limit (which bounds every body)."""
        if max_bytes > self.max_upload_bytes:
            max_bytes, why = self.max_upload_bytes, UPLOAD_SETTING
        return BodyBudget(max_bytes, why, True, values, containers, objects, strings)

    def for_request(self, path: str, content_type: bytes | None) -> BodyBudget:
        """The budget of a request to `path` with this Content-Type."""
        if is_multipart(content_type) and _UPLOAD_RE.fullmatch(path):
            return self.upload
        if _POINT_RE.fullmatch(path):
            return self.points
        return self.general


def size_refusal(budget: BodyBudget, size: int | None = None) -> Refusal:
    """413 for a body over the budget's bytes (`size` when it was declared up front)."""
    what = "JSON request body" if budget.json else "request body"
    got = f" of {size} bytes" if size is not None else ""
    return Refusal(413, "too-large", f"{what}{got} exceeds the limit of {budget.max_bytes} "
                   f"bytes for this route ({budget.why})")


def shape_refusal(budget: BodyBudget, shape: JsonShape) -> Refusal | None:
    """Why a JSON body (so far) is past its budget of values, containers or depth; or None."""
    if not budget.json:
        return None
    if shape.has_nul:
        return Refusal(422, "validation-error",
                       "JSON request body is not UTF-8 text (it holds a NUL byte)")
    if shape.max_depth > budget.max_depth:
        return Refusal(422, "validation-error",
                       f"JSON request body nests arrays/objects more than {budget.max_depth} "
                       "levels deep")
    for count, limit, what in ((shape.values, budget.max_values, "values"),
                               (shape.containers, budget.max_containers, "arrays/objects")):
        if count > limit:  # too much to parse: the body is too large for what it holds
            return Refusal(413, "too-large",
                           f"JSON request body holds more than {limit} {what}, the most this "
                           f"route takes ({budget.why})")
    for count, limit, what in ((shape.objects, budget.max_objects, "objects"),
                               (shape.strings, budget.max_strings, "strings (keys included)")):
        if count > limit:  # a route of numbers sent other kinds of values: invalid content
            return Refusal(422, "validation-error",
                           f"JSON request body holds more than {limit} {what}, the most this "
                           f"route takes ({budget.why})")
    return None
