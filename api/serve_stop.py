"""How `phasecal serve` stops on SIGINT and SIGTERM: jobs at once, everything else in order.

On a stop signal uvicorn stops accepting connections and waits for the open ones to end
before the app's shutdown (`Services.close`) runs. A client following a job (SSE) keeps
its stream open until the job ends, and a camera preview until the client leaves (the
server never stopped while the operator's page showed the camera). So the jobs are
interrupted as soon as the signal arrives (their event streams send `end`), then every
response still streaming sees its client hang up (`StreamsEndOnStop`) and ends as it does
for a real hang-up; a request still open after `GRACE_S` is cut by uvicorn.

uvicorn's own handling would also make a second Ctrl-C skip the app's shutdown (rigs and
database left open, worker processes left to the interpreter's exit) and raise the caught
signal again at the end, which ended the process by SIGTERM (status -15, skipping the
interpreter's exit) or by a KeyboardInterrupt. Here a repeated signal changes nothing (the
stop is bounded), nothing is raised again, and a requested stop exits 0.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

import uvicorn
from fastapi import FastAPI

log = logging.getLogger("phasecal.service")

#: the signals that stop the service in order (systemd's stop, kill, a terminal's Ctrl-C)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: seconds open connections (a slow upload, a hung request) get before they are cut
GRACE_S = 5
#: seconds between the jobs' end (their event streams send `end`) and the streams' hang-up
STREAMS_LINGER_S = 0.5

Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
DISCONNECT: Message = {"type": "http.disconnect"}


class StreamsEndOnStop:
    """ASGI wrapper: after `stop()`, a response that has started sees its client hang up.

    Only a response already sent its start reads `receive` for a hang-up (a stream); a
    request still reading its body is not touched. A stream ended this way gets the last,
    empty body part from here, so the server does not log an incomplete response.
    """

    def __init__(self, app: Callable[[Message, Receive, Send], Awaitable[None]]) -> None:
        self.app = app
        self.loop: asyncio.AbstractEventLoop | None = None
        self.stopping: asyncio.Event | None = None

    def stop(self) -> None:
        """Hang up on every started response (thread-safe; nothing before any request or
        once the server's loop has ended)."""
        if self.loop is None or self.stopping is None:
            return
        try:
            self.loop.call_soon_threadsafe(self.stopping.set)
        except RuntimeError:  # the loop is closed: the server is done, no stream is open
            pass

    async def __call__(self, scope: Message, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if self.stopping is None:
            self.loop, self.stopping = asyncio.get_running_loop(), asyncio.Event()
        stopping = self.stopping
        state = {"started": False, "complete": False, "hung_up": False}

        async def tracked_send(message: Message) -> None:
            if message["type"] == "http.response.start":
                state["started"] = True
            elif message["type"] == "http.response.body" and not message.get("more_body"):
                state["complete"] = True
            await send(message)

        async def receive_or_stop() -> Message:
            if not state["started"]:
                return await receive()
            if stopping.is_set():
                state["hung_up"] = True
                return DISCONNECT
            got = asyncio.ensure_future(receive())
            stop = asyncio.ensure_future(stopping.wait())
            try:
                await asyncio.wait({got, stop}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                stop.cancel()
            if got.done():
                return got.result()
            got.cancel()
            state["hung_up"] = True
            return DISCONNECT

        await self.app(scope, receive_or_stop, tracked_send)
        if state["hung_up"] and state["started"] and not state["complete"]:
            await send({"type": "http.response.body", "body": b"", "more_body": False})


class ServiceServer(uvicorn.Server):
    """uvicorn's server whose stop signal also calls `on_stop` (stop the jobs) at once, then
    ends the app's open streams (`streams`, the wrapper the app is served through)."""

    def __init__(self, config: uvicorn.Config, on_stop: Callable[[], None],
                 streams: StreamsEndOnStop) -> None:
        super().__init__(config)
        self.on_stop = on_stop
        self.streams = streams
        #: the stop signals received, in order (what `phasecal serve` prints at the end)
        self.stop_signals: list[signal.Signals] = []

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        """Ask the server to stop (the first signal) and the jobs to stop, from a thread:
        a signal handler must return at once."""
        name = signal.Signals(sig)
        if name not in self.stop_signals:
            self.stop_signals.append(name)
        if self.should_exit:
            return
        self.should_exit = True
        threading.Thread(target=self.stop_jobs, name="phasecal-stop-jobs", daemon=True).start()

    def stop_jobs(self) -> None:
        """`on_stop` (logged if it fails: the app's shutdown stops the jobs again), then,
        once the ended jobs' event streams have had `STREAMS_LINGER_S` to send `end`, every
        stream still open sees its client hang up."""
        try:
            self.on_stop()
        except Exception:
            log.exception("stopping the jobs on a stop signal failed")
        time.sleep(STREAMS_LINGER_S)
        self.streams.stop()

    @contextmanager
    def stop_signals_handled(self) -> Iterator[None]:
        """`handle_exit` for `STOP_SIGNALS` also outside uvicorn's own handling (before it
        starts serving, after it has shut down); the previous handlers after. Main thread
        only (elsewhere signals cannot be handled)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {sig: signal.signal(sig, self.handle_exit) for sig in STOP_SIGNALS}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


def serve(app: FastAPI, host: str, port: int, on_stop: Callable[[], None]) -> ServiceServer:
    """Run `app` on host:port until a stop signal; the server (its `started` and
    `stop_signals` say how it went)."""
    streams = StreamsEndOnStop(app)
    config = uvicorn.Config(streams, host=host, port=port, log_level="warning",
                            timeout_graceful_shutdown=GRACE_S)
    server = ServiceServer(config, on_stop, streams)
    with server.stop_signals_handled():
        server.run()
    return server
