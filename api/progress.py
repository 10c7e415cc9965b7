"""Progress bars for long CLI commands (rich), silent when the output is not a terminal.

`with progress_bar("decode") as update: update(done, total, stage)`: the callback has the
signature of the numerics' `progress(done, total, message)` hooks, so it plugs straight in.
Logs, pipes and CI output stay free of bar redraws.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

from calibration.shared.progress import ProgressFn


@contextmanager
def progress_bar(label: str, stream: TextIO | None = None) -> Iterator[ProgressFn]:
    """A live bar on `stream` (default stderr) if it is a terminal; else a no-op callback."""
    out = stream if stream is not None else sys.stderr
    if not out.isatty():
        yield lambda done, total, stage: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    console = Console(file=out, force_terminal=True)
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console) as prog:
        task = prog.add_task(label, total=None)

        def update(done: int, total: int, stage: str) -> None:
            prog.update(task, completed=done, total=total if total > 0 else None,
                        description=f"{label}: {stage}" if stage not in ("", label) else label)

        yield update
