"""What the commands print: tables (rich if installed, else plain text), lines, JSON, poses; and
:class:`Elapsed`, a long command's running time on stderr."""

from __future__ import annotations

import json
import math
import sys
import threading
import time

import torch

from .. import so3


def _console():
    try:
        from rich.console import Console
    except ImportError:  # rich is an optional extra: fall back to plain text
        return None
    return Console(width=None if sys.stdout.isatty() else 160)  # pipes and files: no 80-column wrap


def table(title: str, columns: list[str], rows: list[list[str]]) -> None:
    """Print a table with rich if it is installed, else as aligned plain text."""
    console = _console()
    if console is not None:
        from rich.table import Table

        rich_table = Table(title=title, title_justify="left")
        for col in columns:
            rich_table.add_column(col, justify="right")
        for row in rows:
            rich_table.add_row(*row)
        console.print(rich_table)
        return
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(columns)]
    print(title)
    for row in [columns, *rows]:
        print("  ".join(cell.rjust(w) for cell, w in zip(row, widths)))


def say(text: str) -> None:
    """Print a line (rich markup such as ``[yellow]`` is rendered by rich, else printed as is)."""
    console = _console()
    console.print(text, highlight=False) if console is not None else print(text)


def print_json(obj) -> None:
    print(json.dumps(obj))


def fmt(values, digits: int = 4) -> list[str]:
    """``values`` as fixed-point text with ``digits`` decimals."""
    # round first and add 0.0 so that values like -1e-17 print as 0.0000, never -0.0000
    return [f"{round(v, digits) + 0.0:.{digits}f}" for v in values]


def pose_summary(pose: torch.Tensor) -> dict:
    """The JSON of a pose ``(4, 4)``: the matrix, ``xyz_m`` and ``rpy_rad``."""
    return {
        "pose": pose.tolist(),
        "xyz_m": pose[:3, 3].tolist(),
        "rpy_rad": so3.matrix_to_rpy(pose[:3, :3]).tolist(),
    }


def print_pose(pose: torch.Tensor, rad: bool, title: str) -> None:
    """A pose ``(4, 4)`` as a table, then its xyz (m) and roll-pitch-yaw (degrees unless ``rad``)."""
    table(title, ["", "c1", "c2", "c3", "c4"], [[f"r{i + 1}", *fmt(row)] for i, row in enumerate(pose.tolist())])
    rpy = so3.matrix_to_rpy(pose[:3, :3]).tolist()
    unit = "rad" if rad else "deg"
    rpy = rpy if rad else [math.degrees(v) for v in rpy]
    say(f"xyz (m): {' '.join(fmt(pose[:3, 3].tolist()))}    rpy ({unit}): {' '.join(fmt(rpy, 3))}")


class Elapsed:
    """A running command's elapsed time on stderr after ``delay`` s: rewritten every second on a
    terminal, else a line every 30 s."""

    def __init__(self, name: str, delay: float = 2.0):
        self.name, self.delay = name, delay
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._start = time.monotonic()
        self._shown = False

    def __enter__(self) -> Elapsed:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        if self._shown and sys.stderr.isatty():
            sys.stderr.write("\r\033[K")  # clear the line for what follows
            sys.stderr.flush()

    def _run(self) -> None:
        tty = sys.stderr.isatty()
        if self._stop.wait(self.delay):
            return
        while True:
            self._shown = True
            text = f"iiwa-torch {self.name}: running for {time.monotonic() - self._start:.0f} s"
            sys.stderr.write(f"\r{text}\033[K" if tty else text + "\n")
            sys.stderr.flush()
            if self._stop.wait(1.0 if tty else 30.0):
                return
