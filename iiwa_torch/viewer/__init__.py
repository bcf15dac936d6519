"""Interactive web viewer of any chain (viser): joint sliders, a pose readout, a draggable IK
target, obstacles and clearance, playback of joint paths.

:func:`show` serves a page (default http://127.0.0.1:8080) with the arm drawn as cylinders
between consecutive frame origins and one short cylinder per joint along its axis (the
skeleton), over a floor grid, and optionally an obstacle :class:`~iiwa_torch.collision.World`,
the robot's collision capsules and its frames. A chain read from a URDF file (``urdf=``) is
drawn with the file's ``<visual>`` meshes and shapes (:func:`iiwa_torch.urdf.read_visuals`,
meshes read by trimesh), or with its fitted capsules if it has none. The side panel has one
slider per joint (degrees, metres for a prismatic joint, within the joint's limits), the
end-effector pose (xyz in metres, roll-pitch-yaw in degrees, ``R = Rz Ry Rx``), the clearance,
the IK controls and status, and a player for paths.

Dragging the target gizmo solves its pose by the gradient IK or the closed form; a target that
cannot be reached within the limits, or only in collision, is coloured and named as such and
the arm keeps its last valid configuration.

Modules: :mod:`.server` (:class:`Viewer`, :func:`show`), :mod:`.scene` (drawing the robot, its
capsules and the obstacles), :mod:`.controls` (joint sliders, readout, display checkboxes),
:mod:`.ik_panel` (drag-to-solve), :mod:`.playback` (paths), :mod:`.world` (:func:`load_world`).
viser is imported when a viewer starts, never when ``iiwa_torch`` is imported.
"""

from .controls import Readout
from .ik_panel import OUTCOMES, TargetResult
from .server import Viewer, show
from .world import load_world

__all__ = ["OUTCOMES", "Readout", "TargetResult", "Viewer", "load_world", "show"]
