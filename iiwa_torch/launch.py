"""Entry point of the ``iiwa-torch`` command (imports no torch itself; see the package docstring).

OpenMP reads its wait policy once, when torch loads: with another busy process on the cores, the
default spin-wait makes batched calls wait on spinning threads (benchmarks/results/busy.md), so the
command asks for ``PASSIVE`` (unless the caller set ``OMP_WAIT_POLICY``) before anything imports torch.
"""

import os


def main() -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from iiwa_torch.cli import main as cli_main

    return cli_main()
