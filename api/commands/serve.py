"""`phasecal serve`: run the REST service (uvicorn) on a rig."""

from __future__ import annotations

import argparse
import dataclasses
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import uvicorn

HELP = "run the REST service (default 127.0.0.1:8000, simulated rig)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="bind address (non-loopback needs a token)")
    p.add_argument("--port", type=int, default=8000, help="TCP port")
    p.add_argument("--rig", default=None, help="'simulated' (default) or a rig .toml/.json file")
    p.add_argument("--rigs-dir", default=None, help="folder of operator rig files "
                   "(*.toml/*.json, one rig each, named by file stem; or PHASECAL_RIGS_DIR): the "
                   "only way besides --rig to use devices or paths GET /devices does not list")
    p.add_argument("--aravis-address", action="append", default=None, metavar="ADDR",
                   help="an Aravis camera (address or id) GET /devices lists and REST rigs may "
                        "use; repeatable (or PHASECAL_ARAVIS_ADDRESSES, comma-separated)")
    p.add_argument("--data-dir", default=None, help="data directory (default ./phasecal-data "
                   "or PHASECAL_DATA_DIR)")
    p.add_argument("--token", default=None, help="API token (visible in ps: prefer "
                   "--token-file or PHASECAL_TOKEN); required for non-loopback hosts")
    p.add_argument("--token-file", default=None, metavar="FILE",
                   help="read the API token from FILE's first line (or PHASECAL_TOKEN_FILE)")
    p.add_argument("--executor", default=None,
                   help="'processes' (default: local worker processes, so numerics never stall "
                        "the API), 'threads' (in the server process), or a Dask scheduler "
                        "tcp://host:port (or PHASECAL_DASK)")


#: the signals that stop the service in order (systemd's stop, kill, a terminal's Ctrl-C)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: uvicorn's exit status when the server never started (port taken, failed startup)
STARTUP_FAILURE = 3


class StopSignals:
    """SIGINT and SIGTERM ask `server` to stop in order, whenever they come.

    uvicorn takes both signals over while it serves, then raises the one it caught again
    to the handler it found: without this one that ended the process by SIGTERM (status
    -15, skipping the interpreter's exit) or by a KeyboardInterrupt. Installed around the
    whole run, this handler is what it finds, so an orderly stop exits 0; before uvicorn
    took over (the app's startup) it asks the server to stop as soon as it has started.
    """

    def __init__(self, server: uvicorn.Server) -> None:
        self.server = server
        self.received: list[signal.Signals] = []

    def __call__(self, sig: int, frame: FrameType | None) -> None:
        name = signal.Signals(sig)
        if name not in self.received:
            self.received.append(name)
        if not self.server.should_exit:
            self.server.handle_exit(sig, frame)

    @contextmanager
    def installed(self) -> Iterator[None]:
        """This handler for `STOP_SIGNALS` (main thread only), the previous ones after."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {sig: signal.signal(sig, self) for sig in STOP_SIGNALS}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


def run(args: argparse.Namespace) -> int:
    import uvicorn  # (lazy: the other commands start without the web stack)

    from api.app import create_app
    from api.config import ServiceConfig, read_token_file

    token = read_token_file(args.token_file) if args.token_file else args.token
    config = ServiceConfig.from_env(host=args.host, port=args.port, rig=args.rig,
                                    data_dir=args.data_dir, token=token,
                                    executor=args.executor, rigs_dir=args.rigs_dir,
                                    aravis_addresses=tuple(args.aravis_address or ()) or None)
    if config.executor is None:  # p99 26 ms vs 295 ms with threads (benchmarks/api.py)
        config = dataclasses.replace(config, executor="processes")
    config.check_security()
    app = create_app(config)
    print(f"phasecal: serving on http://{config.host}:{config.port} "
          f"(data {config.data_dir.resolve()}, rig {config.rig})", flush=True)
    server = uvicorn.Server(uvicorn.Config(app, host=config.host, port=config.port,
                                           log_level="warning"))
    stops = StopSignals(server)
    with stops.installed():
        server.run()
    if not server.started:
        return STARTUP_FAILURE
    if stops.received:
        print(f"phasecal: stopped on {', '.join(s.name for s in stops.received)}", flush=True)
    return 0
