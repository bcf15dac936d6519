"""iiwa-torch: batched, differentiable robot kinematics in PyTorch."""

from . import collision, robots, so3
from .dh import Convention, DHChain

__all__ = ["Convention", "DHChain", "collision", "robots", "so3"]
__version__ = "0.1.0"
