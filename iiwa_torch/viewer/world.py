"""The viewer's obstacles: :func:`load_world` (the ``--world`` JSON of docs/viewer.md) and :func:`unbatched`."""

from __future__ import annotations

import json
import numbers
from pathlib import Path

import numpy as np
import torch

from .. import collision, so3

_F64 = torch.float64


def load_world(spec) -> collision.World:
    """An obstacle world from a dict, a JSON text (starting with ``{``) or a JSON file path.

    Keys, all optional (m; degrees): ``floor`` (height or null; default 0), ``spheres`` ``[[x, y, z, r]]``,
    ``boxes`` ``[[x, y, z, hx, hy, hz(, roll, pitch, yaw)]]`` (half extents), ``capsules``
    ``[[x1, y1, z1, x2, y2, z2, r]]``, ``walls`` ``[[nx, ny, nz, offset]]`` (free where ``n . x >= offset``).
    """
    spec = _spec(spec)
    kwargs = {"floor": spec.get("floor", 0.0)}
    if (s := _rows(spec, "spheres", (4,))) is not None:
        kwargs["spheres"] = (s[:, :3].contiguous(), s[:, 3].contiguous())
    if (b := _rows(spec, "boxes", (6, 9))) is not None:
        pose = torch.eye(4, dtype=_F64).repeat(len(b), 1, 1)
        pose[:, :3, 3] = b[:, :3]
        if b.shape[1] == 9:
            pose[:, :3, :3] = so3.rpy_to_matrix(torch.deg2rad(b[:, 6:9]))
        kwargs["boxes"] = (pose, b[:, 3:6].contiguous())
    if (c := _rows(spec, "capsules", (7,))) is not None:
        kwargs["capsules"] = (c[:, :6].reshape(-1, 2, 3), c[:, 6].contiguous())
    if (w := _rows(spec, "walls", (4,))) is not None:
        norm = w[:, :3].norm(dim=-1, keepdim=True)
        if not bool((norm > 1e-9).all()):
            raise ValueError(f"world: a wall normal must be nonzero, got {w[:, :3].tolist()}")
        kwargs["walls"] = (w[:, :3] / norm, w[:, 3].contiguous())
    return collision.World(**kwargs)


def _spec(spec) -> dict:
    """``spec`` as a dict with known keys only (JSON text and files parsed)."""
    if isinstance(spec, (str, Path)):
        text = str(spec)
        if not text.lstrip().startswith("{"):
            path = Path(text)
            if not path.is_file():
                raise ValueError(f"world {text!r} is neither a JSON object nor an existing file")
            try:
                text = path.read_text()
            except UnicodeDecodeError:
                raise ValueError(f"world file {text!r} is not JSON text") from None
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"world: invalid JSON ({err})") from None
    if not isinstance(spec, dict):
        raise TypeError(f"world must be a dict, JSON text or file path, got {type(spec).__name__}")
    known = {"floor", "spheres", "boxes", "capsules", "walls"}
    if set(spec) - known:
        raise ValueError(f"world: unknown keys {sorted(set(spec) - known)}; known: {sorted(known)}")
    return spec


def _rows(spec: dict, kind: str, widths: tuple[int, ...]) -> torch.Tensor | None:
    """``spec[kind]`` as a float64 ``(k, max width)`` tensor (shorter rows padded with 0), None if absent."""
    items = spec.get(kind)
    if not items:
        return None
    if not isinstance(items, (list, tuple)):
        raise ValueError(f"world: {kind} must be a list of rows of numbers, got {items!r}")
    bad = [row for row in items if not isinstance(row, (list, tuple)) or len(row) not in widths]
    if bad:
        raise ValueError(f"world: each of {kind} needs {' or '.join(map(str, widths))} numbers, got {bad[0]}")
    if any(isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) for row in items for v in row):
        raise ValueError(f"world: {kind} must hold numbers, got {items}")
    width = max(len(row) for row in items)
    rows = torch.tensor([list(row) + [0.0] * (width - len(row)) for row in items], dtype=_F64)
    if not bool(rows.isfinite().all()):
        raise ValueError(f"world: {kind} must be finite numbers, got {items}")
    return rows


def unbatched(world: collision.World) -> collision.World:
    """``world`` in float64 on the CPU; ValueError if it holds a batch of obstacle sets."""
    parts = {}
    for kind, lead in (("walls", 2), ("spheres", 2), ("boxes", 3), ("capsules", 3)):
        pair = getattr(world, kind)
        if pair is not None:
            if pair[0].ndim != lead:
                raise ValueError(f"the viewer draws one obstacle set: {kind}[0] must have {lead} dims, "
                                 f"got shape {tuple(pair[0].shape)}")  # fmt: skip
            parts[kind] = tuple(t.detach().to("cpu", _F64) for t in pair)
    return collision.World(floor=world.floor, **parts)
