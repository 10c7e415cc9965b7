"""A lab's own robot server as a `Mover`: a small HTTP/JSON protocol (docs/robots.md).

    GET  /info   -> {"name", "axes", "repeatability": {"mm", "deg"}, "workspace": {...}}
    GET  /pose   -> {"R": 3x3, "t_mm": [3]}                  the pose the robot reports
    POST /move   {"R", "t_mm", "timeout_s"} -> 200 {"R", "t_mm"} once settled;
                 422 {"error"} refused (nothing moved); 504 {"error"} timed out (the server
                 stopped the robot); 409 {"error"} stopped by /stop
    POST /stop   -> 200 {}                                   halt at once, also when idle

Every request has a timeout; a move whose answer does not come within its own timeout
plus `margin_s` is stopped by this client (POST /stop) and reported as MoveTimeout.
`acquisition/movers/http_server.py` serves any `Mover` this way.
"""

from __future__ import annotations

from typing import Any

import httpx

from acquisition.mover import (
    MoveRefused,
    MoverError,
    MoverInfo,
    MoveStopped,
    MoveTimeout,
    RobotPose,
)


class HttpMover:
    """Client of a robot server at `url` (e.g. http://robot.lab:8100)."""

    def __init__(self, url: str, *, request_timeout_s: float = 5.0, margin_s: float = 2.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        self.url = url.rstrip("/")
        self._request_timeout_s = request_timeout_s
        self._margin_s = margin_s
        self._client = httpx.Client(base_url=self.url, timeout=request_timeout_s,
                                    transport=transport)
        self._info = MoverInfo.from_json(self._call("GET", "/info"), f"{self.url}/info")

    @property
    def info(self) -> MoverInfo:
        return self._info

    def _call(self, method: str, path: str, body: dict[str, Any] | None = None,
              timeout_s: float | None = None) -> Any:
        """One request; MoverError naming the server for anything but a 200 with JSON."""
        try:
            resp = self._client.request(method, path, json=body,
                                        timeout=timeout_s or self._request_timeout_s)
        except httpx.TimeoutException:
            raise  # the caller decides: a move is stopped, a query is a MoverError
        except httpx.HTTPError as exc:
            raise MoverError(f"robot server {self.url}{path}: {exc}") from None
        try:
            data = resp.json()
        except ValueError:
            raise MoverError(f"robot server {self.url}{path}: HTTP {resp.status_code}, "
                             "not JSON") from None
        if resp.status_code == 200:
            return data
        error = data.get("error") if isinstance(data, dict) else None
        message = f"robot server {self.url}: {error or f'HTTP {resp.status_code}'}"
        errors = {422: MoveRefused, 504: MoveTimeout, 409: MoveStopped}
        raise errors.get(resp.status_code, MoverError)(message)

    def move_to(self, pose: RobotPose, timeout_s: float) -> RobotPose:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s: expected > 0, got {timeout_s}")
        try:
            data = self._call("POST", "/move", {**pose.to_json(), "timeout_s": timeout_s},
                              timeout_s=timeout_s + self._margin_s)
        except httpx.TimeoutException:
            self.stop()
            raise MoveTimeout(f"robot server {self.url}: no answer to the move within "
                              f"{timeout_s + self._margin_s:.3g} s; sent stop") from None
        return RobotPose.from_json(data, f"{self.url}/move reply")

    def current_pose(self) -> RobotPose:
        try:
            return RobotPose.from_json(self._call("GET", "/pose"), f"{self.url}/pose")
        except httpx.TimeoutException:
            raise MoverError(f"robot server {self.url}/pose: no answer within "
                             f"{self._request_timeout_s:g} s") from None

    def stop(self) -> None:
        try:
            self._call("POST", "/stop", {})
        except httpx.TimeoutException:
            raise MoverError(f"robot server {self.url}/stop: no answer within "
                             f"{self._request_timeout_s:g} s: stop the robot by hand") from None

    def close(self) -> None:
        self._client.close()
