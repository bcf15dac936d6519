"""The crossovers of two internal path thresholds, each path timed on the same inputs.

    python benchmarks/bench_paths.py [--quick]

- ``so3._RIGID_NUMPY_BATCH``: ``check_rigid`` of up to that many CPU poses runs in numpy (one pose
  in Python floats) instead of torch. Every checked pose input goes through it (``ik.solve``,
  ``pose_error``, the trajectories), so its fixed cost is paid by every one-target call.
- ``ik.dls._LAPACK_BATCH``: up to that many problems the DLS solve uses LAPACK's Cholesky per
  matrix, above it the entry-by-entry one batched over the problems (the torch LM loop's).

For each batch size both paths are timed (one thread, ``common.timeit``) by setting the threshold
to force one or the other. Writes results/paths.json and results/paths.md.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import torch  # noqa: E402
from common import command, machine, markdown_table, save, timeit  # noqa: E402

from iiwa_torch import robots, so3  # noqa: E402
from iiwa_torch.ik import dls  # noqa: E402

BATCHES = (1, 2, 8, 32, 64, 128, 256, 384, 512, 1024, 4096)
DTYPES = (torch.float64, torch.float32)


def rigid_call(batch: int, dtype: torch.dtype):
    """``check_rigid`` of ``batch`` iiwa 14 end poses."""
    chain = robots.iiwa14()
    pose = chain.fk(chain.random_q(batch, generator=torch.Generator().manual_seed(0), dtype=dtype))
    return lambda: so3.check_rigid(pose)


def dls_call(batch: int, dtype: torch.dtype):
    """``dls_step_batch_last`` of ``batch`` random 6 x 7 problems (the LM loop's shapes)."""
    gen = torch.Generator().manual_seed(0)
    J, rhs = torch.randn(6, 7, batch, generator=gen, dtype=dtype), torch.randn(6, 1, batch, generator=gen, dtype=dtype)
    damping = torch.full((batch,), 1e-4, dtype=dtype)
    return lambda: dls.dls_step_batch_last(J, rhs, damping, torch.finfo(dtype).tiny)


#: threshold -> (module, attribute, the call, name of the path below it, name above it)
THRESHOLDS = {
    "so3._RIGID_NUMPY_BATCH": (so3, "_RIGID_NUMPY_BATCH", rigid_call, "numpy", "torch"),
    "ik.dls._LAPACK_BATCH": (dls, "_LAPACK_BATCH", dls_call, "LAPACK", "unrolled"),
}


def measure(min_time: float) -> dict:
    """``{threshold: {dtype: {batch: (below µs, above µs)}}}``: each call timed down both paths."""
    out = {}
    for name, (module, attribute, make, _, _) in THRESHOLDS.items():
        kept = getattr(module, attribute)
        out[name] = {}
        try:
            for dtype in DTYPES:
                rows = out[name][str(dtype)] = {}
                for batch in BATCHES:
                    call = make(batch, dtype)
                    times = []
                    for threshold in (1 << 62, 0):  # every batch below it, then none
                        setattr(module, attribute, threshold)
                        times.append(timeit(call, min_time=min_time) * 1e6)
                    rows[batch] = times
                    print(name, dtype, batch, [f"{t:.1f} µs" for t in times], flush=True)
        finally:
            setattr(module, attribute, kept)
    return out


def markdown(results: dict, cmd: str) -> str:
    parts = [f"`{cmd}`: each call timed down both paths of a threshold (one thread, `common.timeit`); "
             "speed-up = the path above the threshold's time / the path below's.\n"]
    for name, (module, attribute, _, below, above) in THRESHOLDS.items():
        parts.append(f"\n## `{name}` (set to {getattr(module, attribute)})\n\n")
        rows = []
        for batch in BATCHES:
            row = [batch]
            for dtype in DTYPES:
                low, high = results["paths"][name][str(dtype)][batch]
                row += [f"{low:.1f}", f"{high:.1f}", f"{high / low:.2f}x"]
            rows.append(row)
        headers = ["batch"] + [f"{h} ({str(d)[6:]})" for d in DTYPES
                               for h in (f"{below} µs", f"{above} µs", f"{below} speed-up")]
        parts.append(markdown_table(headers, rows))
    parts.append(f"\nMachine: {results['machine']}\n")
    return "".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter repeats")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = {"machine": machine(), "paths": measure(0.02 if args.quick else 0.2)}
    results["machine"]["loadavg_at_end"] = list(os.getloadavg())
    md = markdown(results, command(__file__))
    print(md)
    print("written:", save("paths_quick" if args.quick else "paths", results, md))


if __name__ == "__main__":
    main()
