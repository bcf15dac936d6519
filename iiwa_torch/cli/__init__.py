"""The ``iiwa-torch`` command: forward and inverse kinematics, trajectories, robot tables, the
workspace, the browser viewer and a demo.

:func:`main` is the command's entry point (the console script, ``python -m iiwa_torch.cli``, or
``main(["fk", ...])`` from code). This module imports no torch: OpenMP reads its wait policy once,
when torch loads, and with another busy process on the cores the default spin-wait makes batched
calls wait on spinning threads (benchmarks/results/busy.md), so :func:`main` asks for ``PASSIVE``
(unless the caller set ``OMP_WAIT_POLICY``) before anything imports torch.

Modules: :mod:`.parser` (the options and the dispatch), :mod:`.arguments` (the robot, angles,
poses and files of the options), :mod:`.output` (tables, JSON, the running time), and the
commands: :mod:`.kinematics` (``fk``, ``ik``, ``robots``), :mod:`.motion` (``traj``, ``demo``),
:mod:`.view`, :mod:`.workspace`.
"""

import os
import sys


def main(argv: list[str] | None = None) -> int:
    """Run ``iiwa-torch argv`` (default: ``sys.argv[1:]``) and return its exit status: 0, 1 when
    ``ik`` finds no valid solution or ``traj`` misses a pose; bad input exits 2 (``SystemExit``)."""
    if "torch" not in sys.modules:  # else its OpenMP runtime has read the policy already
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .parser import run

    return run(argv)
