"""JSON request bodies built to amplify in memory: status, time and the server's RSS growth.

`json.loads` turns `{}` (3 bytes) into a 64-byte dict, so a JSON body costs the server many
times its size once parsed. Each case POSTs one body shape to a running `phasecal serve`
(with Content-Length, and chunked so that only the streamed bytes tell its size) and reads
the server process's peak RSS from /proc; the shapes are 50 MB bodies and bodies just
under the default JSON limit (which the value/nesting budget must stop). The run closes
with two legitimate large requests (the largest preset plan, 200,000 points for project)
and 200,000 points that each fail validation.

    .venv/bin/python benchmarks/reliability_bodies.py

`run_body_cases(base_url, server_pid)` returns one row per case: shape, bytes, status,
seconds (until the status line arrived), rss_growth_mb (the server's peak resident memory
during the case above its resident memory before the first case, so memory kept from an
earlier case counts against later ones) and held (refused with 413/422 within a second
and at most 100 MB of growth, 5 s for 200,000 invalid rows, which fit every budget and are
parsed; for the legitimate cases: answered as a valid request);
also expected (the statuses that hold), attack (held to time and memory too) and
peak_reset (False where /proc would not reset the peak: growth is then since start).
"""

from __future__ import annotations

import argparse
import json
import select
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquisition.patterns import PRESETS, build_plan  # noqa: E402
from api.config import DEFAULT_MAX_JSON_BYTES  # noqa: E402
from benchmarks.serve_process import start_serve  # noqa: E402

ATTACK_BYTES = 50 << 20
NEAR_LIMIT_BYTES = DEFAULT_MAX_JSON_BYTES - (64 << 10)
MAX_GROWTH_MB = 100.0
MAX_SECONDS = 1.0
SEND_PIECE = 1 << 16
UNKNOWN_CAL = "/calibrations/cal_0000000000000000"


@dataclass(frozen=True)
class Case:
    """One request: what it is, where it goes, its body, and the statuses that hold."""

    shape: str
    path: str
    body: bytes
    chunked: bool
    expect: tuple[int, ...]
    attack: bool  # also held to max_seconds and MAX_GROWTH_MB
    max_seconds: float = MAX_SECONDS


def _fill(prefix: bytes, item: bytes, last: bytes, suffix: bytes, size: int) -> bytes:
    """prefix + item repeated + last + suffix, about `size` bytes in all."""
    count = max(0, (size - len(prefix) - len(last) - len(suffix)) // len(item))
    return prefix + item * count + last + suffix


PLAN_HEAD = b'{"plan": {"format": "phasecal.plan/1", '
SHAPES: dict[str, Callable[[int], tuple[str, bytes]]] = {
    "plan frames [{},...]": lambda n: ("/sessions", _fill(
        PLAN_HEAD + b'"frames": [', b"{},", b"{}", b"]}}", n)),
    "plan deep [[[[...]]]]": lambda n: ("/sessions", PLAN_HEAD + b'"x": '
                                        + b"[" * ((n - 60) // 2) + b"]" * ((n - 60) // 2)
                                        + b"}}"),
    "long name string": lambda n: ("/sessions", _fill(b'{"name": "', b"a", b"", b'"}', n)),
    "plan many keys": lambda n: ("/sessions", PLAN_HEAD + b", ".join(
        b'"k%08d": 0' % i for i in range((n - 60) // 16)) + b"}}"),
    "plan numbers [0,...]": lambda n: ("/sessions", _fill(
        PLAN_HEAD + b'"frames": [', b"0,", b"0", b"]}}", n)),
    "plan strings [\"\",...]": lambda n: ("/sessions", _fill(
        PLAN_HEAD + b'"frames": [', b'"",', b'""', b"]}}", n)),
    "points [[0,0,0],...]": lambda n: (f"{UNKNOWN_CAL}/project", _fill(
        b'{"points": [', b"[0,0,0],", b"[0,0,0]", b"]}", n)),
    "points as objects": lambda n: (f"{UNKNOWN_CAL}/project", b'{"points": [' + b",".join(
        b'{"%040d": 0.5}' % i for i in range((n - 20) // 48)) + b"]}"),
}


def legitimate_cases() -> list[Case]:
    """The largest preset plan (on a 16K screen) and MAX_POINTS points for project."""
    from api.schemas import MAX_POINTS

    biggest = max((build_plan(15360, 8640, [0.1, 0.1], preset=p) for p in PRESETS),
                  key=lambda plan: len(plan.frames))
    plan = json.dumps({"name": "largest preset", "plan": biggest.to_dict()}, indent=2)
    row = [-123.45678901234568, 98.765432109876543, 1234.5678901234568]
    # as a client library sends them (13 MB: within a 16 MiB upload limit too)
    points = json.dumps({"points": [row] * MAX_POINTS})
    bad_rows = json.dumps({"points": [[False, 0, 1]] * MAX_POINTS})
    # an unknown calibration answers 404 only after the body passed every limit and check
    return [Case("largest preset plan", "/sessions", plan.encode(), False, (201,), False),
            Case(f"{MAX_POINTS} points", f"{UNKNOWN_CAL}/project", points.encode(),
                 False, (404,), False),
            # within every budget, so it is parsed (about a second on a loaded machine)
            Case(f"{MAX_POINTS} rows, each invalid", f"{UNKNOWN_CAL}/project",
                 bad_rows.encode(), False, (422,), True, max_seconds=5.0)]


def body_cases(attack_bytes: int = ATTACK_BYTES,
               near_limit_bytes: int = NEAR_LIMIT_BYTES) -> list[Case]:
    """Every shape at `attack_bytes` (declared, then chunked) and just under the JSON limit."""
    cases = []
    for shape, make in SHAPES.items():
        path, body = make(attack_bytes)
        cases.append(Case(shape, path, body, False, (413,), True))
        cases.append(Case(shape + ", chunked", path, body, True, (413, 422), True))
    for shape, make in SHAPES.items():
        path, body = make(near_limit_bytes)
        cases.append(Case(shape + ", under the limit", path, body, False, (413, 422), True))
    return cases


def post_raw(base_url: str, path: str, body: bytes, chunked: bool,
             timeout_s: float = 120.0) -> tuple[int, float]:
    """POST a JSON body over a plain socket; (status, seconds until the status line).

    Stops sending as soon as the server answers (a refusal before the whole body is sent
    is what a limit is for); an HTTP client library would insist on sending it all first.
    """
    url = urlsplit(base_url)
    host, port = url.hostname or "127.0.0.1", url.port or 80
    framing = b"Transfer-Encoding: chunked" if chunked else b"Content-Length: %d" % len(body)
    head = (b"POST %s HTTP/1.1\r\nHost: %s:%d\r\nContent-Type: application/json\r\n%s\r\n"
            b"Connection: close\r\n\r\n" % (path.encode(), host.encode(), port, framing))
    reply = b""
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        start = time.perf_counter()
        try:
            sock.sendall(head)
            for at in range(0, len(body), SEND_PIECE):
                if select.select([sock], [], [], 0)[0]:
                    break  # the server answered before the body was complete
                piece = body[at:at + SEND_PIECE]
                sock.sendall(b"%x\r\n%s\r\n" % (len(piece), piece) if chunked else piece)
            else:
                if chunked:
                    sock.sendall(b"0\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed; its answer is still in our receive buffer
        while b"\r\n" not in reply:
            data = sock.recv(65536)
            if not data:
                break
            reply += data
        seconds = time.perf_counter() - start
    status = reply.split(b"\r\n", 1)[0].split()
    return (int(status[1]) if len(status) > 1 else 599), seconds


def _status_kb(pid: int, field: str) -> int:
    """One `VmXXX:  N kB` field of /proc/PID/status."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/{pid}/status has no {field}")


def reset_peak(pid: int) -> bool:
    """Reset the process's peak RSS (VmHWM) to its current RSS; False if not permitted."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def run_body_cases(base_url: str, server_pid: int, cases: list[Case] | None = None
                   ) -> list[dict]:
    """Send every case to the server at `base_url` (process `server_pid`); one row each."""
    cases = body_cases() + legitimate_cases() if cases is None else cases
    # warm up: the first session and project requests import modules and open the database
    post_raw(base_url, "/sessions", b'{"preset": "fast"}', False)
    post_raw(base_url, f"{UNKNOWN_CAL}/project", b'{"points": [[0, 0, 1]]}', False)
    time.sleep(0.2)
    baseline_kb = _status_kb(server_pid, "VmRSS")
    rows = []
    for case in cases:
        can_reset = reset_peak(server_pid)
        status, seconds = post_raw(base_url, case.path, case.body, case.chunked)
        time.sleep(0.05)  # let the server finish the request it answered
        peak_kb = _status_kb(server_pid, "VmHWM")
        growth = max(0, peak_kb - baseline_kb) / 1024
        held = status in case.expect
        if case.attack:
            held = held and seconds <= case.max_seconds and growth <= MAX_GROWTH_MB
        rows.append({"shape": case.shape, "bytes": len(case.body), "status": status,
                     "seconds": round(seconds, 3), "rss_growth_mb": round(growth, 1),
                     "held": held, "expected": list(case.expect), "attack": case.attack,
                     "peak_reset": can_reset})
    return rows


def print_table(rows: list[dict]) -> None:
    """The rows as an aligned text table."""
    print(f"{'shape':44s} {'bytes':>10s} {'status':>6s} {'seconds':>8s} {'RSS +MB':>8s}  held")
    for r in rows:
        print(f"{r['shape']:44s} {r['bytes']:>10d} {r['status']:>6d} {r['seconds']:>8.3f} "
              f"{r['rss_growth_mb']:>8.1f}  {'yes' if r['held'] else 'NO'}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--attack-mb", type=float, default=ATTACK_BYTES / 2**20)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="phasecal-bodies-") as tmp:
        proc, url = start_serve(Path(tmp) / "data", executor="threads")
        try:
            rows = run_body_cases(url, proc.pid,
                                  body_cases(int(args.attack_mb * 2**20)) + legitimate_cases())
        finally:
            proc.terminate()
            proc.wait(30)
    print_table(rows)
    if not all(r["peak_reset"] for r in rows):
        print("(peak RSS could not be reset: growth is the peak since the server started)")
    return 0 if all(r["held"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
