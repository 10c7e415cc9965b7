"""CLI start-up: `phasecal --help` against `python -c "import numpy, cv2"` (goal:
within 2.5x). Runs each command N times in fresh processes, alternating, and prints the
medians, their ratio and the load average (the ratio is what to compare across machines).

    .venv/bin/python benchmarks/cli_startup.py [--runs 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

BASELINE = [sys.executable, "-c", "import numpy, cv2"]
_SCRIPT = Path(sys.executable).with_name("phasecal")  # the installed console script
HELP = [str(_SCRIPT), "--help"] if _SCRIPT.exists() else [sys.executable, "-m", "api.cli", "--help"]
TARGET = 2.5


def _time(cmd: list[str]) -> float:
    """Wall seconds of one fresh process running `cmd` (output discarded; must succeed)."""
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs of each command (default 7)")
    args = parser.parse_args()
    _time(BASELINE), _time(HELP)  # warm the file cache
    base, cli = [], []
    for _ in range(args.runs):
        base.append(_time(BASELINE))
        cli.append(_time(HELP))
    b, c = statistics.median(base), statistics.median(cli)
    ratio = c / b
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print("| command | median s | min s |")
    print("|---|---:|---:|")
    print(f"| python -c \"import numpy, cv2\" | {b:.3f} | {min(base):.3f} |")
    print(f"| phasecal --help | {c:.3f} | {min(cli):.3f} |")
    print(f"\nratio (median) {ratio:.2f}x (target <= {TARGET}x: "
          f"{'met' if ratio <= TARGET else 'NOT met'}); runs {args.runs}; load {load}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
