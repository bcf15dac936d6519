"""iiwa-torch: batched, differentiable robot kinematics in PyTorch.

Names are loaded on first use (PEP 562), so that ``iiwa_torch.cli.main`` can set OpenMP's wait
policy before anything imports torch.
"""

from __future__ import annotations

import importlib

__all__ = ["Chain", "Convention", "DHChain", "JointKind", "collision", "robots", "so3"]
__version__ = "0.1.0"

_HOMES = {"Chain": ".chain", "JointKind": ".chain", "Convention": ".dh", "DHChain": ".dh"}


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name], __name__), name)
    if name in __all__:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
