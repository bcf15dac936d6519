"""Optional compiled kernels (numba) for the small-batch CPU paths: one configuration's end pose
and Jacobian, the Levenberg-Marquardt rounds of :func:`~iiwa_torch.ik.solve`, the arm-angle
sweep of :func:`~iiwa_torch.ik.analytic.iiwa_solve` and the closed form of
:func:`~iiwa_torch.ik.analytic.pieper`; and for large CPU batches without autograd, the self and
floor :func:`~iiwa_torch.collision.clearance`.

numba is an optional extra (``pip install iiwa-torch[fast]``). This package only looks for
it; :func:`kernels` imports numba and the kernels (:mod:`iiwa_torch.compiled.numba_kernels`) on
the first call that uses them, never at ``import iiwa_torch``, and each kernel compiles on its
first call (``cache=True``: numba's on-disk cache serves later processes). Without numba, or
with the environment variable ``IIWA_TORCH_NUMBA=0``, :data:`ENABLED` is False and the callers
run their torch code instead (or numpy, where docs/kinematics.md lists a kept twin): the same
method, which the kernels restate.
"""

from __future__ import annotations

import importlib.util
import os

__all__ = ["ENABLED", "kernels"]

#: Whether the kernels run: numba is installed and ``IIWA_TORCH_NUMBA`` is not ``"0"``.
ENABLED = os.environ.get("IIWA_TORCH_NUMBA", "1") != "0" and importlib.util.find_spec("numba") is not None

_LOADED: list = []


def kernels():
    """:mod:`iiwa_torch.compiled.numba_kernels`, imported (numba with it) on the first call."""
    if not _LOADED:
        from . import numba_kernels

        _LOADED.append(numba_kernels)
    return _LOADED[0]
