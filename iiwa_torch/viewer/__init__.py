"""Interactive web viewer of any chain (viser): joint sliders, a pose readout, a draggable IK target,
obstacles and clearance, playback of joint paths (docs/viewer.md).

Modules: :mod:`.server` (:class:`Viewer`, :func:`show`), :mod:`.scene`, :mod:`.controls`,
:mod:`.ik_panel`, :mod:`.playback`, :mod:`.world`. viser is imported when a viewer starts.
"""

from .controls import Readout
from .ik_panel import OUTCOMES, TargetResult
from .server import Viewer, show
from .world import load_world

__all__ = ["OUTCOMES", "Readout", "TargetResult", "Viewer", "load_world", "show"]
