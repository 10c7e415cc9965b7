"""Property-based check of the whole OpenAPI document with schemathesis: no 5xx, no violation."""

from __future__ import annotations

import tempfile
from pathlib import Path

import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis import checks

from api.app import create_app
from api.config import ServiceConfig

_DATA = Path(tempfile.mkdtemp(prefix="phasecal-schemathesis-"))
APP = create_app(ServiceConfig(data_dir=_DATA, max_upload_bytes=1 << 20))
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


@schema.parametrize()
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_openapi_conformance(case: schemathesis.Case) -> None:
    # positive_data_acceptance is excluded: semantic rules (a plan's completeness, ids that
    # exist, plan xor preset) cannot be written in JSON Schema and rightly answer 4xx.
    case.call_and_validate(excluded_checks=[checks.positive_data_acceptance])


def test_openapi_document_is_complete() -> None:
    doc = APP.openapi()
    paths = doc["paths"]
    for path in ("/sessions", "/sessions/{session_id}/poses", "/sessions/{session_id}/poses/import",
                 "/sessions/{session_id}/calibrations", "/calibrations/{cal_id}/unproject",
                 "/jobs", "/jobs/{job_id}/events", "/jobs/{job_id}/cancel", "/rigs", "/devices"):
        assert path in paths, path
    examples = doc["components"]["schemas"]["CalibrationCreate"].get("examples")
    assert examples and examples[0]["model"] == "opencv-rational"
