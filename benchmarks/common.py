"""Shared plumbing for the benchmarks: timing, machine facts, JSON/markdown output.

Each benchmark sets ``OMP_WAIT_POLICY=PASSIVE`` before it imports torch: with another
process busy on the cores, OpenMP's spin-wait made 2-thread ops ~100x slower here.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def timeit(fn, *, min_time: float = 0.2, repeats: int = 5, max_calls: int | None = None) -> float:
    """Median over ``repeats`` of the mean seconds per call, each repeat running ``fn``
    for at least ``min_time`` seconds (or ``max_calls`` calls). One warm-up call first."""
    fn()
    samples = []
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while True:
            fn()
            calls += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_time or (max_calls is not None and calls >= max_calls):
                break
        samples.append(elapsed / calls)
    return statistics.median(samples)


def save(name: str, payload: dict, markdown: str) -> Path:
    """Write ``results/<name>.json`` and ``results/<name>.md``; return the JSON path."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(markdown)
    return path


def markdown_table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
