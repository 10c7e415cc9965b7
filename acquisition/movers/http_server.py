"""Serve any `Mover` over the HTTP/JSON robot protocol of `acquisition.movers.http`.

For a lab that drives its robot from Python: wrap the driver in a `Mover` and serve it, and
`HttpMover` (or any other client of the protocol) controls it from the calibration host.
Moves run in the request's thread, so /stop, served by another thread, interrupts them.
"""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from acquisition.mover import Mover, MoveRefused, MoveStopped, MoveTimeout, RobotPose


class MoverServer:
    """`mover` served on host:port (port 0: a free one) until `close()`."""

    def __init__(self, mover: Mover, host: str = "127.0.0.1", port: int = 0) -> None:
        self.mover = mover
        self._httpd = ThreadingHTTPServer((host, port), _handler_for(mover))
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True,
                                        name="mover-server")
        self._thread.start()

    @property
    def url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host}:{port}"

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join()


def _handler_for(mover: Mover) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: Any) -> None:
            """Quiet: a robot server's callers log what matters."""

        def _reply(self, status: int, body: Any) -> None:
            data = json.dumps(body).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self) -> None:
            if self.path == "/info":
                self._reply(200, mover.info.to_json())
            elif self.path == "/pose":
                self._reply(200, mover.current_pose().to_json())
            else:
                self._reply(404, {"error": f"no such resource {self.path}"})

        def do_POST(self) -> None:
            length = int(self.headers.get("Content-Length") or 0)
            try:
                body = json.loads(self.rfile.read(length) or b"{}")
            except ValueError:
                self._reply(400, {"error": "body is not JSON"})
                return
            if self.path == "/stop":
                mover.stop()
                self._reply(200, {})
            elif self.path == "/move":
                self._move(body)
            else:
                self._reply(404, {"error": f"no such resource {self.path}"})

        def _move(self, body: Any) -> None:
            try:
                pose = RobotPose.from_json(body, "move")
                timeout_s = float(body.get("timeout_s", 30.0))
                self._reply(200, mover.move_to(pose, timeout_s).to_json())
            except (MoveRefused, ValueError) as exc:
                self._reply(422, {"error": str(exc)})
            except MoveTimeout as exc:
                self._reply(504, {"error": str(exc)})
            except MoveStopped as exc:
                self._reply(409, {"error": str(exc)})

    return Handler
