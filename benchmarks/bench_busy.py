"""The same ``ik.solve`` call alone and beside a busy process, per OpenMP wait policy and thread count.

    python benchmarks/bench_busy.py [--quick] [--note TEXT]

``ik.solve`` on 10,000 random reachable iiwa 14 poses (float64 targets, the library's defaults),
median of 3 timed calls after a warm-up. Each configuration runs in a fresh Python process,
because OpenMP reads ``OMP_WAIT_POLICY`` once, when torch loads: the wait policy unset
(OpenMP's default) or ``PASSIVE``, 1 thread or 2 (torch's default here is one per core), and
the machine as it is ("alone") or with a second process, started by this script, spinning
on one core ("busy"). Rounds alternate alone and busy so drift of the load hits both.
Writes results/busy.json and results/busy.md (``_quick`` with ``--quick``); ``--note`` goes
into the table's header (e.g. what else ran on the machine).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys

from common import Clock, markdown_table, save

BURNER = "while True: pass"


def child(n: int, repeats: int, threads: int) -> dict:
    """In the fresh process: time ``ik.solve`` on ``n`` targets; wall and CPU seconds per call."""
    import torch

    from iiwa_torch import robots
    from iiwa_torch.ik import solve

    torch.set_num_threads(threads)
    chain = robots.iiwa14()
    target = chain.fk(chain.random_q(n, generator=torch.Generator().manual_seed(0)))
    solve(chain, target[:8])  # warm-up
    walls, cpus, result = [], [], None
    for _ in range(repeats):
        clock = Clock()
        result = solve(chain, target)
        wall, cpu = clock.stop()
        walls.append(wall)
        cpus.append(cpu)
    return {
        "seconds": statistics.median(walls),
        "cpu seconds": statistics.median(cpus),
        "all seconds": walls,
        "success": float(result.success.double().mean()),
        "torch threads": torch.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
    }


def run_one(policy: str | None, threads: int, busy: bool, n: int, repeats: int) -> dict:
    """One configuration in a fresh interpreter, with a spinning process beside it if ``busy``."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    burner = subprocess.Popen([sys.executable, "-c", BURNER]) if busy else None
    try:
        load = os.getloadavg()[0]
        cmd = [sys.executable, __file__, "--child", str(n), str(repeats), str(threads)]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()
    return {
        "policy": policy or "default",
        "threads": threads,
        "load": "busy" if busy else "alone",
        "loadavg at start": load,
        **json.loads(out.splitlines()[-1]),
    }


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1,000 targets, one timed call (a smoke run)")
    parser.add_argument("--note", default="", help="a sentence for the table's header (what else ran)")
    parser.add_argument("--child", nargs=3, type=int, metavar=("N", "REPEATS", "THREADS"), help=argparse.SUPPRESS)
    return parser.parse_args()


def markdown(rows: list[dict], n: int, repeats: int, command: str, note: str, machine: dict) -> str:
    """The table of every configuration, each against the same policy and threads alone."""
    alone = {(r["policy"], r["threads"]): r["seconds"] for r in rows if r["load"] == "alone"}
    table = [
        [
            r["policy"],
            r["threads"],
            r["load"],
            f"{r['loadavg at start']:.1f}",
            f"{r['seconds']:.3f}",
            f"{r['cpu seconds']:.3f}",
            f"{r['seconds'] / alone[r['policy'], r['threads']]:.1f}x",
            f"{100 * r['success']:.2f}%",
        ]
        for r in rows
    ]
    md = [
        f"# `ik.solve` alone and beside a busy process (`{command}`)\n\n",
        f"{n:,} random reachable iiwa 14 poses, float64 targets, library defaults; median of {repeats} "
        "timed call(s) per configuration, each configuration in a fresh process. busy: a second Python "
        "process spins on one core for the whole configuration. load average: 1-minute, at the start.\n\n",
    ]
    if note:
        md.append(f"{note}\n\n")
    headers = ["OMP_WAIT_POLICY", "torch threads", "load", "load average", "seconds (wall)", "seconds (CPU)",
               "busy / alone", "success 0.1 mm / 1 mrad"]  # fmt: skip
    md.append(markdown_table(headers, table))
    md.append(
        f"\nMachine: {machine['cpu']}, {machine['cpu_count']} CPUs, torch {machine['torch']}, {machine['date']}.\n"
    )
    return "".join(md)


def main() -> None:
    args = parse_args()
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    n, repeats = (1_000, 1) if args.quick else (10_000, 3)
    from iiwa_torch.runtime import machine_info  # imports torch: only after the children ran

    rows = []
    for policy, threads in itertools.product([None, "PASSIVE"], [1, 2]):
        for busy in (False, True):
            rows.append(run_one(policy, threads, busy, n, repeats))
            print(rows[-1], flush=True)
    command = f"python benchmarks/bench_busy.py{' --quick' if args.quick else ''}"
    machine = machine_info() | {"OMP_WAIT_POLICY": "set per configuration (column policy)"}
    md = markdown(rows, n, repeats, command, args.note, machine)
    path = save(
        "busy_quick" if args.quick else "busy",
        {"command": command, "note": args.note, "machine": machine, "rows": rows},
        md,
    )
    print(md)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
