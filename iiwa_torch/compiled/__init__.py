"""Optional numba kernels for the small-batch CPU paths (end pose and Jacobian, ``ik.solve``'s LM rounds,
``iiwa_solve``'s sweep, ``pieper``) and the large-batch self and floor ``collision.clearance``.

numba is an optional extra (``pip install iiwa-torch[fast]``), imported by :func:`kernels` on first use, never at
``import iiwa_torch``; kernels compile on first call (``cache=True``). Without numba, or with ``IIWA_TORCH_NUMBA=0``,
:data:`ENABLED` is False and the callers run their torch (or numpy) code, the same method.
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
