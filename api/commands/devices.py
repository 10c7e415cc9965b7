"""`phasecal devices`: list displays and cameras a rig config could use."""

from __future__ import annotations

import argparse
import dataclasses
import json

from acquisition.discovery import list_devices
from acquisition.errors import CameraError
from api.cli import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--aravis", action="store_true",
                   help="also run Aravis discovery (broadcasts on every network interface)")
    p.add_argument("--aravis-address", action="append", default=[], metavar="ADDR",
                   help="probe an Aravis camera at this address or id, without discovery")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")


def run(args: argparse.Namespace) -> int:
    try:
        found = list_devices(aravis_discovery=args.aravis, aravis_addresses=args.aravis_address)
    except CameraError as exc:
        raise UserError(str(exc)) from exc
    if args.json:
        print(json.dumps([dataclasses.asdict(d) for d in found], indent=2))
        return 0
    rows = [("KIND", "BACKEND", "ID", "DESCRIPTION")]
    rows += [(d.kind, d.backend, d.id, d.description) for d in found]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r[:3], widths, strict=True)) + "  " + r[3])
    return 0
