"""`phasecal serve`: run the REST service (uvicorn) on a rig."""

from __future__ import annotations

import argparse
import dataclasses

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


#: uvicorn's exit status when the server never started (port taken, failed startup)
STARTUP_FAILURE = 3


def run(args: argparse.Namespace) -> int:
    from api.app import create_app  # (lazy: the other commands start without the web stack)
    from api.config import ServiceConfig, read_token_file
    from api.serve_stop import serve

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
    # SIGTERM/SIGINT: jobs interrupted at once, then an orderly stop and exit 0 (serve_stop)
    services = app.state.services
    server = serve(app, config.host, config.port, on_stop=services.jobs.shutdown)
    if not server.started:  # (e.g. the port is taken): uvicorn ran no app shutdown
        services.close()
        return STARTUP_FAILURE
    if server.stop_signals:
        print(f"phasecal: stopped on {', '.join(s.name for s in server.stop_signals)}",
              flush=True)
    return 0
