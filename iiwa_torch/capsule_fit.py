"""Capsules for any URDF arm, fitted to its ``<collision>`` geometry (:func:`urdf_capsules`).

Each element becomes balls whose hull holds it (a sphere; a cylinder's two end balls; box
corners; mesh hull vertices); each link's capsule is a small-volume one around its balls, its
radius then grown to the farthest ball, so containment holds by construction. docs/collision.md.
"""

from __future__ import annotations

import itertools
import math
import os

import numpy as np
import torch

from .chain import Chain
from .checks import check_instance, check_nonnegative, check_positive
from .collision import Capsules, World, pairwise_clearance
from .urdf import UrdfCollision, read_collisions, read_urdf

__all__ = ["urdf_capsules"]

_GRID = 24  # radii tried per axis, twice (coarse, then around the best)


def _element_balls(element: UrdfCollision) -> tuple[np.ndarray, np.ndarray]:
    """Balls, centres ``(N, 3)`` and radii ``(N,)`` in the element's frame, whose convex hull holds it."""
    if element.shape == "mesh":
        mesh = element.load_mesh()
        hull = mesh.convex_hull if len(mesh.vertices) >= 4 else mesh
        points = np.asarray(hull.vertices, dtype=np.float64) * np.asarray(element.size)
    elif element.shape == "box":
        points = np.array(list(itertools.product((-0.5, 0.5), repeat=3))) * np.asarray(element.size)
    elif element.shape == "sphere":
        return np.zeros((1, 3)), np.array(element.size)
    else:  # cylinder: radius, length along z
        radius, length = element.size
        return np.array([[0.0, 0.0, -length / 2], [0.0, 0.0, length / 2]]), np.full(2, radius)
    return points, np.zeros(len(points))


def _link_points(elements) -> tuple[np.ndarray, np.ndarray]:
    """Balls (centres ``(N, 3)``, radii ``(N,)``, m) enclosing one link's ``elements`` at every pose, in
    their chain frame."""
    centres, radii = [], []
    for element in elements:
        points, radius = _element_balls(element)
        for pose in element.poses:
            matrix = np.asarray(pose)
            centres.append(points @ matrix[:3, :3].T + matrix[:3, 3])
            radii.append(radius)
    return np.concatenate(centres), np.concatenate(radii)


def _volume(radius, length):
    return math.pi * radius**2 * length + 4.0 / 3.0 * math.pi * radius**3


def _fit_along(origin: np.ndarray, axis: np.ndarray, centres: np.ndarray, radii: np.ndarray):
    """The smallest capsule on the line ``origin + t axis`` (unit) holding the balls, the radius from two
    grids: ``(volume, t0, t1, radius)``."""
    rel = centres - origin
    t = rel @ axis  # (N,)
    d = np.linalg.norm(rel - t[:, None] * axis, axis=1)
    low = float(np.max(d + radii))
    span = float(t.max() - t.min()) + 1e-12

    def lengths(r):  # r (G,) -> the segment ends each radius needs
        reach = np.sqrt(np.maximum((r[:, None] - radii) ** 2 - d**2, 0.0))  # (G, N)
        return (t + reach).min(1), (t - reach).max(1)

    best = None
    lo, hi = low, low + span
    for _ in range(2):
        r = np.linspace(lo, hi, _GRID)
        start, end = lengths(r)
        volume = _volume(r, np.maximum(end - start, 0.0))
        k = int(np.argmin(volume))
        if best is None or volume[k] < best[0]:
            best = (float(volume[k]), float(start[k]), float(end[k]), float(r[k]))
        step = (hi - lo) / (_GRID - 1)
        lo, hi = max(low, r[k] - step), r[k] + step
    return best


def _enclosing_capsule(centres, radii=None, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """A small capsule holding every ball (``centres (N, 3)``, ``radii (N,)``, default 0) -> ends ``a, b (3,)``
    and radius (m).

    Axes tried: the centres' principal directions, the coordinate axes and 64 spread directions;
    the three best are refined by random turns and shifts (``seed``) while the volume drops."""
    centres = np.asarray(centres, dtype=np.float64)
    radii = np.zeros(len(centres)) if radii is None else np.asarray(radii, dtype=np.float64)
    mean = centres.mean(0)
    _, _, principal = np.linalg.svd(centres - mean, full_matrices=False)
    turns = np.pi * (3.0 - math.sqrt(5.0)) * np.arange(64)  # a Fibonacci sphere of 64 directions
    z = np.linspace(1 - 1 / 64, -1 + 1 / 64, 64)
    spread = np.stack([np.sqrt(1 - z**2) * np.cos(turns), np.sqrt(1 - z**2) * np.sin(turns), z], 1)
    axes = np.concatenate([principal, np.eye(3), spread])
    scale = float(np.ptp(centres, 0).max() + radii.max()) or 1.0

    def centred(axis):  # the line through the middle of the balls' shadow on the plane normal to axis
        rel = centres - mean
        flat = rel - (rel @ axis)[:, None] * axis
        return mean + (flat.max(0) + flat.min(0)) / 2

    starts = sorted(((_fit_along(centred(a), a, centres, radii), centred(a), a) for a in axes), key=lambda s: s[0][0])
    rng = np.random.default_rng(seed)
    best = starts[0]
    for fit, origin, axis in starts[:3]:
        step = 0.3
        while step > 1e-3:
            improved = False
            for _ in range(8):
                turn = rng.normal(size=3)
                shift = rng.normal(size=3) * scale
                trial_axis = axis + step * turn
                trial_axis /= np.linalg.norm(trial_axis)
                trial_origin = origin + 0.1 * step * shift
                trial = _fit_along(trial_origin, trial_axis, centres, radii)
                if trial[0] < fit[0]:
                    fit, origin, axis, improved = trial, trial_origin, trial_axis, True
            if not improved:
                step /= 2
        if fit[0] < best[0][0]:
            best = (fit, origin, axis)
    (_, t0, t1, _), origin, axis = best
    if t1 < t0:
        t0 = t1 = (t0 + t1) / 2
    a, b = origin + t0 * axis, origin + t1 * axis
    return a, b, float(np.max(_distance_to_segment(centres, a, b) + radii))


def _distance_to_segment(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances ``(N,)`` from ``points (N, 3)`` to the segment ``a b``."""
    d = b - a
    length = float(d @ d)
    s = np.clip((points - a) @ d / length, 0.0, 1.0) if length > 0 else np.zeros(len(points))
    return np.linalg.norm(points - a - s[:, None] * d, axis=1)


def urdf_capsules(
    chain: Chain,
    source: str | os.PathLike,
    *,
    base_link: str | None = None,
    pairs=None,
    samples: int = 10000,
    margin: float = 0.05,
    seed: int = 0,
) -> Capsules:
    """A capsule, named by its link, for each link of ``chain`` with ``<collision>`` geometry in the URDF
    ``source`` that ``chain`` was read from (same ``base_link``).

    Self pairs (``pairs=None``), as MoveIt's ``disable_collisions``: all but those in one frame,
    adjacent links, and pairs that overlap in all of ``samples`` random configurations (``seed``)
    or never come within ``margin`` (m). ``pairs``: your own, as link-name pairs. Every capsule
    but the base frame's faces the floor. Raises ``ValueError`` if ``chain`` is not ``source``'s
    path or a link in ``pairs`` has no capsule."""
    check_instance(chain, Chain, "chain")
    check_positive(samples, "samples", integer=True)
    check_nonnegative(margin, "margin")
    check_nonnegative(seed, "seed", integer=True)
    try:
        path = read_urdf(source, end_link=chain.link_names[-1], base_link=base_link)
    except ValueError as err:
        raise ValueError(f"chain {chain.name!r} does not match source: {err}") from None
    origins = torch.tensor([j.origin for j in path.joints], dtype=torch.float64)
    if [j.name for j in path.joints] != list(chain.joint_names) or not torch.allclose(
        origins, chain.origins.detach().cpu().double(), atol=1e-9
    ):
        raise ValueError(f"chain {chain.name!r} is not the path of source from {path.base_link!r} to "
                         f"{path.end_link!r}; pass the base_link it was read with")
    elements = read_collisions(source, end_link=path.end_link, base_link=path.base_link)
    links = list(dict.fromkeys(e.link for e in elements))
    if not links:
        raise ValueError("source has no <collision> geometry on the chain's links")
    frames, ends, radii = [], [], []
    for link in links:
        mine = [e for e in elements if e.link == link]
        a, b, r = _enclosing_capsule(*_link_points(mine), seed=seed)
        frames.append(mine[0].frame)
        ends.append(np.stack([a, b]))
        radii.append(r)
    floor = [f != 0 for f in frames]
    model = Capsules.build(chain, links, frames, np.stack(ends), radii, pairs=(), floor=floor)
    if pairs is None:
        adjacent = {frozenset((j.parent, j.child)) for j in path.joints}
        candidates = [(i, j) for i, j in itertools.combinations(range(len(links)), 2)
                      if frames[i] != frames[j] and frozenset((links[i], links[j])) not in adjacent]
        chosen = _sampled_pairs(chain, model, candidates, samples, margin, seed)
    else:
        chosen = _named_pairs(pairs, links)
    return Capsules.build(chain, links, frames, np.stack(ends), radii, pairs=chosen, floor=floor)


def _sampled_pairs(chain: Chain, model: Capsules, candidates, samples: int, margin: float, seed: int):
    """The ``candidates`` apart in some of ``samples`` configurations and within ``margin`` in some."""
    if not candidates:
        return ()
    trial = Capsules.build(chain, model.names, model.frames, model.points, model.radii, pairs=candidates,
                           floor=model.floor)
    q = chain.random_q(samples, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        gaps = pairwise_clearance(chain, q, World(floor=None), trial).distance  # (samples, P)
    keep = ((gaps >= 0).any(0) & (gaps.amin(0) <= margin)).tolist()
    return tuple(pair for pair, ok in zip(candidates, keep) if ok)


def _named_pairs(pairs, links: list[str]) -> tuple[tuple[int, int], ...]:
    """Link-name pairs as sorted capsule index pairs."""
    index = {name: i for i, name in enumerate(links)}
    chosen = []
    for pair in pairs:
        if len(pair) != 2 or any(name not in index for name in pair) or pair[0] == pair[1]:
            raise ValueError(f"pairs must be pairs of two different links with capsules ({', '.join(links)}), "
                             f"got {tuple(pair)}")
        chosen.append(tuple(sorted((index[pair[0]], index[pair[1]]))))
    return tuple(dict.fromkeys(chosen))
