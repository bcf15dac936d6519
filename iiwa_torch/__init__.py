"""iiwa-torch: batched, differentiable robot kinematics in PyTorch."""

from . import robots, so3
from .dh import Convention, DHChain

__all__ = ["Convention", "DHChain", "robots", "so3"]
__version__ = "0.1.0"
