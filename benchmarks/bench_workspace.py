"""Workspace sampling rate and the time to the iiwa 14's volume within 1%.

    python benchmarks/bench_workspace.py [--quick]

Measures the rate (configurations per second, one thread) of sampling reachable points
(flange: ``chain.position``; wrist centre: ``chain.fk`` and a point in the flange frame)
and of sampling plus binning on the side-view grid, then the wall time of
``workspace.volume`` for the wrist centre at decreasing cell sizes ``h``: the first whose
bracket half-width is within 1% of the estimate is the "time to 1%". Writes
results/workspace.json and results/workspace.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import torch  # noqa: E402
from common import markdown_table, save, timeit  # noqa: E402

from iiwa_torch import robots  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402
from iiwa_torch.workspace import DATASHEET, frame_point, occupancy, sample_points, volume  # noqa: E402

CHAIN = robots.iiwa14()


def sampling_rates(block: int, wrist: torch.Tensor) -> dict[str, float]:
    """Configurations per second (one thread) of each sampler on blocks of ``block``."""
    gen = torch.Generator().manual_seed(0)
    samplers = {
        "flange points (position, float32)": lambda: sample_points(CHAIN, block, generator=gen),
        "wrist-centre points (fk, float32)": lambda: sample_points(CHAIN, block, point=wrist, generator=gen),
        "wrist centre, sampled + binned (rz, h = 5 mm)": lambda: occupancy(
            CHAIN, block, 0.005, section="rz", point=wrist, generator=gen
        ),
    }
    rates = {}
    for name, fn in samplers.items():
        rates[name] = block / timeit(fn, min_time=0.2, repeats=3)
        print(f"{name:50s} {rates[name] / 1e6:6.2f} M configurations/s")
    return rates


def volume_runs(sizes: list[float], wrist: torch.Tensor) -> tuple[list[dict], float | None]:
    """``workspace.volume`` of the wrist centre at each cell size ``h`` (m): one record each (its
    estimate, bracket, half-width and wall seconds), and the seconds of the first within 1% (or None)."""
    runs, time_to_1pc = [], None
    for h in sizes:
        start = time.perf_counter()
        v = volume(CHAIN, h, section="rz", point=wrist, generator=torch.Generator().manual_seed(1))
        seconds = time.perf_counter() - start
        half = (v.high - v.low) / 2 / v.estimate
        runs.append({"h": h, "seconds": seconds, **dataclasses.asdict(v), "half_width": half})
        print(
            f"h = {h * 1000:g} mm: {v.estimate:.4f} m^3 [{v.low:.4f}, {v.high:.4f}] +-{half:.2%}, "
            f"{v.n_samples} samples, {seconds:.2f} s"
        )
        if time_to_1pc is None and half <= 0.01:
            time_to_1pc = seconds
    return runs, time_to_1pc


def markdown(quick: bool, info: dict, rates: dict[str, float], runs: list[dict], time_to_1pc: float | None) -> str:
    table = [
        [
            f"{r['h'] * 1000:g}",
            f"{r['estimate']:.4f}",
            f"[{r['low']:.4f}, {r['high']:.4f}]",
            f"{r['half_width']:.2%}",
            r["n_samples"],
            f"{r['seconds']:.2f}",
        ]
        for r in runs
    ]
    return (
        f"# Workspace benchmark ({'quick' if quick else 'full'})\n\n"
        f"Machine: {info}\n\n"
        + markdown_table(["sampler (1 thread)", "rate"], [[k, f"{v / 1e6:.2f} M/s"] for k, v in rates.items()])
        + "\nVolume of the iiwa 14's wrist-centre workspace (datasheet: "
        f"{DATASHEET['iiwa14']['volume']} m^3), side-view grid:\n\n"
        + markdown_table(["h (mm)", "estimate (m^3)", "bracket", "half-width", "samples", "seconds"], table)
        + f"\nTime to a volume within 1%: {'not reached' if time_to_1pc is None else f'{time_to_1pc:.2f} s'}\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller blocks and two cell sizes (a smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    wrist = frame_point(CHAIN, 5)
    rates = sampling_rates(1 << 16 if args.quick else 1 << 20, wrist)
    runs, time_to_1pc = volume_runs([0.01, 0.005] if args.quick else [0.01, 0.005, 0.004, 0.003], wrist)
    info = machine_info()
    path = save(
        "workspace",
        {
            "machine": info,
            "quick": args.quick,
            "rates_per_second": rates,
            "volume_runs": runs,
            "seconds_to_1_percent": time_to_1pc,
        },
        markdown(args.quick, info, rates, runs, time_to_1pc),
    )
    print(f"time to 1%: {time_to_1pc}; wrote {path}")


if __name__ == "__main__":
    main()
