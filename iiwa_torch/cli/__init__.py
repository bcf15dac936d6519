"""The ``iiwa-torch`` command: kinematics, trajectories, robot tables, the workspace, the viewer, a demo.

This module imports no torch: OpenMP reads its wait policy once, when torch loads, and the default
spin-wait stalls batched calls when another process is busy on the cores (benchmarks/results/busy.md),
so :func:`main` sets ``PASSIVE`` (unless ``OMP_WAIT_POLICY`` is set) before torch is imported.
"""

import os
import sys


def main(argv: list[str] | None = None) -> int:
    """Run ``iiwa-torch argv`` (default ``sys.argv[1:]``); exit status 0, or 1 when ``ik`` finds no valid
    solution or ``traj`` misses a pose. Bad input raises ``SystemExit(2)``."""
    if "torch" not in sys.modules:  # else its OpenMP runtime has read the policy already
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .parser import run

    return run(argv)
