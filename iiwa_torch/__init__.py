"""iiwa-torch: batched, differentiable robot kinematics in PyTorch.

Names are loaded on first use (PEP 562), so that ``iiwa_torch.launch`` can set OpenMP's wait
policy before anything imports torch.
"""

from __future__ import annotations

import importlib

__all__ = ["Convention", "DHChain", "collision", "robots", "so3"]
__version__ = "0.1.0"

_FROM_DH = {"Convention", "DHChain"}


def __getattr__(name: str):
    if name in _FROM_DH:
        return getattr(importlib.import_module(".dh", __name__), name)
    if name in __all__:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
