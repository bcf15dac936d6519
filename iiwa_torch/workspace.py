"""Reachable workspace and dexterity of a chain, by sampling in-limit configurations in blocks.

Points are binned on a grid of side ``h`` (m): ``Section.XYZ`` voxels (m^3), ``Section.XY`` the
projection on the x-y plane (m^2), ``Section.RZ`` the side view ``(r, z)``, each cell a ring about
the world z axis (m^3). Boundary cells count half; see docs/workspace.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .chain import Chain
from .checks import as_point, check_bool, check_generator, check_instance, check_positive, is_integer, require

__all__ = [
    "Section",
    "Occupancy",
    "Volume",
    "Extent",
    "Dexterity",
    "DexterityMap",
    "DATASHEET",
    "frame_point",
    "sample_points",
    "occupancy",
    "volume",
    "extent",
    "envelopes",
    "dexterity",
    "dexterity_map",
    "plot_workspace",
]

# KUKA's LBR iiwa datasheet (workspace table, as reproduced in the appendix of A. C. Pereira
# et al., "Modelagem Robô KUKA LBR iiwa"): side-view dimensions A-G in mm, volume in m^3.
DATASHEET = {
    "iiwa7": {"A": 1266, "B": 1140, "C": 340, "D": 400, "E": 400, "F": 260, "G": 800, "volume": 1.7},
    "iiwa14": {"A": 1306, "B": 1180, "C": 360, "D": 420, "E": 400, "F": 255, "G": 820, "volume": 1.8},
}


class Section(str, Enum):
    """The grid: 3-D voxels, the x-y plane, or the side view (r, z)."""

    XYZ = "xyz"
    XY = "xy"
    RZ = "rz"


@dataclass(frozen=True)
class Occupancy:
    """Hit counts ``(nx, ny, nz)`` (XYZ), ``(nx, ny)`` (XY) or ``(nr, nz)`` (RZ) int64 on a grid of
    side ``h`` (m); cell ``i`` along axis ``k`` starts at ``lower[k] + i h``."""

    section: Section
    h: float
    lower: tuple[float, ...]
    counts: np.ndarray
    n_samples: int
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, in the end-effector frame: whose reach is counted

    @property
    def occupied(self) -> np.ndarray:
        return self.counts > 0

    def cell_measure(self) -> np.ndarray:
        """Volume (m^3) or area (m^2) of each cell, broadcastable to ``counts``."""
        h = self.h
        if self.section is Section.XYZ:
            return np.full((1, 1, 1), h**3)
        if self.section is Section.XY:
            return np.full((1, 1), h**2)
        r_mid = (np.arange(self.counts.shape[0]) + 0.5) * h
        return (2 * math.pi * r_mid * h**2)[:, None]

    def boundary(self) -> np.ndarray:
        """Occupied cells with an unoccupied face neighbour (outside the grid is unoccupied, except
        across the RZ section's axis r = 0, which mirrors onto itself)."""
        occ = self.occupied
        inner = occ.copy()
        for axis in range(occ.ndim):
            pad = [(0, 0)] * occ.ndim
            pad[axis] = (1, 1)
            p = np.pad(occ, pad, constant_values=False)
            if self.section is Section.RZ and axis == 0:
                p[0] = p[1]
            n = occ.shape[axis]
            inner &= np.take(p, range(0, n), axis=axis) & np.take(p, range(2, n + 2), axis=axis)
        return occ & ~inner


@dataclass(frozen=True)
class Volume:
    """Workspace volume (m^3; m^2 for ``Section.XY``): ``estimate`` counts boundary cells half,
    ``low``/``high`` not at all/fully. ``missing_mass``: Good-Turing estimate (cells hit once /
    samples) of the chance of a new cell; ``converged``: the last doubling moved it less than ``tol``."""

    estimate: float
    low: float
    high: float
    h: float
    n_samples: int
    missing_mass: float
    converged: bool


@dataclass(frozen=True)
class Extent:
    """Highest and lowest sampled ``z`` and largest distance ``r_max`` from the z axis (m), in the base
    frame (:func:`_base_rz`)."""

    z_max: float
    z_min: float
    r_max: float
    n_samples: int


@dataclass(frozen=True)
class Dexterity:
    """Per configuration ``(...)``: manipulability (the product of J's singular values),
    condition number ``sigma_max / sigma_min`` (inf at a singularity: ``sigma_min`` within rounding of 0,
    below ``sigma_max * max(rows, n) * eps``) and ``sigma_min``."""

    manipulability: Tensor
    condition: Tensor
    sigma_min: Tensor


@dataclass(frozen=True)
class DexterityMap:
    """Manipulability ``mean`` and ``max`` ``(nr, nz)`` over the side view (0 where ``count`` is 0),
    cells of side ``h`` (m) from ``r = 0``, ``z = z_lower``."""

    h: float
    z_lower: float
    count: np.ndarray
    mean: np.ndarray
    max: np.ndarray


def frame_point(chain: Chain, frame: int, *, trials: int = 64, tol: float = 1e-9) -> Tensor:
    """Origin of frame ``frame`` (index of ``fk_all``) in end-effector coordinates, ``(3,)`` m float64.

    Raises ValueError unless it is fixed in the end-effector frame (e.g. the iiwa's wrist centre, frame 5).
    """
    check_instance(chain, Chain, "chain")
    n = chain.n_joints
    if not is_integer(frame) or not 0 <= frame <= n:
        raise ValueError(f"frame must be an integer in 0..{n}, got {frame!r}")
    check_positive(trials, "trials", integer=True)
    check_positive(tol, "tol")
    q = chain.random_q(trials, generator=torch.Generator().manual_seed(0))
    origin = chain.fk_all(q)[:, frame, :, 3]  # (trials, 4)
    local = torch.linalg.solve(chain.fk(q), origin.unsqueeze(-1)).squeeze(-1)[:, :3]
    spread = (local - local[0]).abs().max().item()
    if spread > tol:
        raise ValueError(
            f"frame {frame}'s origin moves in the end-effector frame by {spread:.3g} m over random "
            f"configurations: it is not a point of the end effector"
        )
    return local.mean(0)


def sample_points(
    chain: Chain,
    n: int,
    *,
    point=None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``(n, 3)`` world positions (m) of ``point`` (``(3,)`` m in the end-effector frame, default its
    origin) at ``n`` uniform in-limit configurations."""
    check_instance(chain, Chain, "chain")
    check_positive(n, "n", integer=True)
    check_generator(generator)
    p = as_point(point)
    q = chain.random_q(int(n), generator=generator, dtype=dtype)
    if not p.any():
        return chain.position(q)
    pose = chain.fk(q)
    return pose[:, :3, 3] + pose[:, :3, :3] @ p.to(dtype)


def _base_rz(chain: Chain, xyz: Tensor) -> Tensor:
    """World points ``xyz (b, 3)`` -> ``(b, 2)``: their distance ``r`` from the base's z axis and their
    height ``z`` along it, from the base origin (m): the RZ section's coordinates."""
    base = chain.base.to(xyz)
    local = (xyz - base[:3, 3]) @ base[:3, :3]
    return torch.stack([torch.hypot(local[:, 0], local[:, 1]), local[:, 2]], 1)


def _cell_index(chain: Chain, xyz: Tensor, section: Section, lower: tuple[float, ...], shape: tuple[int, ...],
                h: float) -> Tensor:
    coords = _base_rz(chain, xyz) if section is Section.RZ else xyz[:, : len(shape)]
    idx = ((coords - torch.tensor(lower, dtype=coords.dtype)) / h).floor().long()
    idx = idx.clamp(min=torch.zeros(len(shape), dtype=torch.long), max=torch.tensor(shape) - 1)
    strides = torch.tensor([math.prod(shape[k + 1 :]) for k in range(len(shape))])
    return (idx * strides).sum(1)


def _blocks(n: int, block: int):
    """Sizes of the blocks of at most ``block`` that make up ``n``."""
    for start in range(0, n, block):
        yield min(block, n - start)


def _grid(chain: Chain, section: Section, h, point, n_samples, block, generator):
    """The sampling arguments checked: ``(point (3,) m, the grid's lower corner, its shape)``."""
    check_instance(chain, Chain, "chain")
    check_positive(h, "h")
    check_positive(n_samples, "n_samples", integer=True)
    check_positive(block, "block", integer=True)
    check_generator(generator)
    p = as_point(point)
    reach = chain.reach_bound(p) + h
    if 2 * reach / h > 2**25:  # first as a float: a tiny h makes it inf
        raise ValueError(f"h = {h} m makes a grid of more than 2**25 cells (reach {reach:.3f} m); use a larger h")
    cells = int(math.ceil(2 * reach / h))
    if section is Section.RZ:
        lower, shape = (0.0, -reach), (int(math.ceil(reach / h)), cells)
    else:
        dims = 3 if section is Section.XYZ else 2
        lower, shape = (-reach,) * dims, (cells,) * dims
    if math.prod(shape) > 2**25:  # int64 counts: 256 MB
        raise ValueError(f"h = {h} m makes a grid of {math.prod(shape)} cells (reach {reach:.3f} m); use a larger h")
    return p, lower, shape


def occupancy(
    chain: Chain,
    n_samples: int,
    h: float,
    *,
    section: Section | str = Section.XYZ,
    point=None,
    block: int = 1 << 20,
    generator: torch.Generator | None = None,
    counts: Occupancy | None = None,
) -> Occupancy:
    """Hit counts of ``n_samples`` points (:func:`sample_points`) on a grid of side ``h`` (m), in
    blocks of ``block`` configurations; ``counts`` continues an earlier result on the same grid."""
    try:
        section = Section(section)
    except ValueError:
        raise ValueError(f"section must be one of {[s.value for s in Section]}, got {section!r}") from None
    p, lower, shape = _grid(chain, section, h, point, n_samples, block, generator)
    total = torch.zeros(math.prod(shape), dtype=torch.int64)
    done = 0
    if counts is not None:
        check_instance(counts, Occupancy, "counts")
        if (counts.section, counts.h, counts.lower, counts.counts.shape) != (section, h, lower, shape):
            raise ValueError("counts is from a different grid (section, h or chain)")
        if counts.point != tuple(p.tolist()):
            raise ValueError(f"counts counts the point {counts.point}, not {tuple(p.tolist())}")
        total += torch.from_numpy(counts.counts.reshape(-1))
        done = counts.n_samples
    for b in _blocks(n_samples, block):
        xyz = sample_points(chain, b, point=p, generator=generator)
        total += torch.bincount(_cell_index(chain, xyz, section, lower, shape, h), minlength=total.numel())
    return Occupancy(section, float(h), lower, total.numpy().reshape(shape), done + n_samples, tuple(p.tolist()))


def _measure(occ: Occupancy) -> tuple[float, float, float]:
    w = occ.cell_measure()
    boundary = occ.boundary()
    interior = occ.occupied & ~boundary
    low = float((interior * w).sum())
    edge = float((boundary * w).sum())
    return low + edge / 2, low, low + edge


def volume(
    chain: Chain,
    h: float = 0.01,
    *,
    section: Section | str = Section.XYZ,
    point=None,
    n_start: int = 1 << 20,
    max_samples: int = 1 << 26,
    tol: float = 2e-3,
    generator: torch.Generator | None = None,
) -> Volume:
    """Workspace volume (m^3; area m^2 for ``Section.XY``) on a grid of side ``h`` (m): ``n_start``
    samples, doubled until the estimate moves less than ``tol`` (relative) or ``max_samples``."""
    check_positive(tol, "tol")
    check_positive(n_start, "n_start", integer=True)
    check_positive(max_samples, "max_samples", integer=True)
    if max_samples < n_start:
        raise ValueError(f"max_samples ({max_samples}) must be at least n_start ({n_start})")
    occ = occupancy(chain, n_start, h, section=section, point=point, generator=generator)
    est, low, high = _measure(occ)
    converged = False
    while not converged and occ.n_samples < max_samples:
        more = min(occ.n_samples, max_samples - occ.n_samples)
        occ = occupancy(chain, more, h, section=section, point=point, generator=generator, counts=occ)
        previous = est
        est, low, high = _measure(occ)
        converged = abs(est - previous) <= tol * est
    missing = float((occ.counts == 1).sum()) / occ.n_samples
    return Volume(est, low, high, occ.h, occ.n_samples, missing, converged)


def envelopes(occ: Occupancy, *, axis_gap: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(z, r_outer, r_inner)`` of an RZ occupancy, each ``(rows,)`` m: the occupied rows' centres and
    the outer and inner edges of their occupied cells. Few samples land in the small ring cells next
    to the axis, so an inner radius under ``axis_gap`` cells is reported as 0."""
    check_instance(occ, Occupancy, "occ")
    if occ.section is not Section.RZ:
        raise ValueError(f"envelopes need an RZ occupancy, got section {occ.section.value!r}")
    if not is_integer(axis_gap) or axis_gap < 0:
        raise ValueError(f"axis_gap must be a non-negative integer (cells), got {axis_gap!r}")
    occ_rz = occ.occupied
    rows = np.flatnonzero(occ_rz.any(0))
    nr = occ_rz.shape[0]
    first = occ_rz[:, rows].argmax(0)
    first[first < axis_gap] = 0
    last = nr - 1 - occ_rz[::-1, rows].argmax(0)
    z = occ.lower[1] + (rows + 0.5) * occ.h
    return z, (last + 1) * occ.h, first * occ.h


def extent(
    chain: Chain, n_samples: int, *, point=None, block: int = 1 << 20, generator: torch.Generator | None = None
) -> Extent:
    """Highest, lowest and farthest-from-the-axis sampled points (m), see :class:`Extent`."""
    check_positive(n_samples, "n_samples", integer=True)
    check_positive(block, "block", integer=True)
    z_max, z_min, r_max = -math.inf, math.inf, 0.0
    for b in _blocks(n_samples, block):
        r, z = _base_rz(chain, sample_points(chain, b, point=point, generator=generator, dtype=torch.float64)).T
        z_max, z_min, r_max = max(z_max, z.max().item()), min(z_min, z.min().item()), max(r_max, r.max().item())
    return Extent(z_max, z_min, r_max, n_samples)


def dexterity(chain: Chain, q: Tensor, *, position_only: bool = False) -> Dexterity:
    """:class:`Dexterity` of the Jacobian at ``q (..., n)`` rad; ``position_only``: its 3 linear rows (m/rad)."""
    check_instance(chain, Chain, "chain")
    check_bool(position_only, "position_only")
    jac = chain.jacobian(q)
    if position_only:
        jac = jac[..., :3, :]
    s = torch.linalg.svdvals(jac)  # (..., min(rows, n)), descending
    sigma_min = s[..., -1]
    manip = s.prod(-1)
    # singular within rounding (numpy's matrix_rank tolerance): a URDF arm's exact singularity leaves
    # sigma_min ~ 1e-16, not 0
    rank_tol = s[..., 0] * max(jac.shape[-2:]) * torch.finfo(s.dtype).eps
    cond = torch.where(sigma_min > rank_tol, s[..., 0] / sigma_min, torch.full_like(sigma_min, math.inf))
    return Dexterity(manip, cond, sigma_min)


def dexterity_map(
    chain: Chain,
    n_samples: int,
    h: float,
    *,
    point=None,
    position_only: bool = False,
    block: int = 1 << 16,
    generator: torch.Generator | None = None,
) -> DexterityMap:
    """Manipulability of ``n_samples`` random configurations, binned by where ``point`` lands in the
    side view on cells of side ``h`` (m)."""
    p, lower, shape = _grid(chain, Section.RZ, h, point, n_samples, block, generator)
    size = math.prod(shape)
    count = torch.zeros(size, dtype=torch.float64)
    total = torch.zeros(size, dtype=torch.float64)
    peak = torch.zeros(size, dtype=torch.float64)
    for b in _blocks(n_samples, block):
        q = chain.random_q(int(b), generator=generator)
        pose = chain.fk(q)
        xyz = pose[:, :3, 3] + pose[:, :3, :3] @ p
        m = dexterity(chain, q, position_only=position_only).manipulability
        idx = _cell_index(chain, xyz, Section.RZ, lower, shape, h)
        count += torch.bincount(idx, minlength=size).double()
        total += torch.bincount(idx, weights=m, minlength=size)
        peak.scatter_reduce_(0, idx, m, reduce="amax")
    mean = torch.where(count > 0, total / count.clamp(min=1), 0.0)
    return DexterityMap(float(h), lower[1], *(t.numpy().reshape(shape) for t in (count, mean, peak)))


def plot_workspace(
    chain: Chain,
    path,
    *,
    manipulability_path=None,
    point=None,
    point_label: str = "flange",
    h: float = 0.005,
    n_samples: int = 1 << 23,
    datasheet: dict | None = None,
    seed: int = 0,
) -> None:
    """Write the side view of ``point``'s reachable set (mirrored, as in KUKA's drawing) with its
    envelopes and ``datasheet``'s marks (a :data:`DATASHEET` entry) to the PNG ``path``; with
    ``manipulability_path``, also the mean and max manipulability over it."""
    keys = set(next(iter(DATASHEET.values())))
    if datasheet is not None and not (isinstance(datasheet, dict) and keys <= set(datasheet)):
        raise ValueError(f"datasheet must be a DATASHEET entry (a dict with {sorted(keys)}), got {datasheet!r}")
    if not is_integer(seed):
        raise TypeError(f"seed must be an integer, got {seed!r}")
    for file in (path, manipulability_path):  # before the sampling, not after it
        if file is not None and not Path(file).resolve().parent.is_dir():
            raise FileNotFoundError(f"the folder of {file} does not exist")
    gen = torch.Generator().manual_seed(seed)
    occ = occupancy(chain, n_samples, h, section=Section.RZ, point=point, generator=gen)
    fig = _figure((10, 6.5), layout="constrained")
    _side_view(fig.add_subplot(), chain, occ, h, point_label, datasheet)
    fig.savefig(path)
    if manipulability_path is None:
        return
    dm = dexterity_map(chain, min(n_samples, 1 << 21), 4 * h, point=point, generator=gen)
    fig = _figure((11, 5.5))
    for k, name in enumerate(("mean", "max")):
        _manipulability_view(fig.add_subplot(1, 2, k + 1), chain, dm, name, point_label)
    fig.tight_layout()
    fig.savefig(manipulability_path)


def _figure(size: tuple[float, float], **kwargs):
    """A ``Figure`` of ``size`` inches at 120 dpi on its own Agg canvas."""
    FigureCanvasAgg = require("matplotlib.backends.backend_agg", "viz").FigureCanvasAgg
    fig = require("matplotlib.figure", "viz").Figure(figsize=size, dpi=120, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def _side_view(ax, chain: Chain, occ: Occupancy, h: float, point_label: str, datasheet: dict | None) -> None:
    est, low, high = _measure(occ)
    z, r_out, r_in = envelopes(occ)
    occ_rz = occ.occupied.T.astype(float)
    image = np.concatenate([occ_rz[:, ::-1], occ_rz], 1)
    nr, nz = occ.counts.shape
    box = (-nr * h, nr * h, occ.lower[1], occ.lower[1] + nz * h)
    ax.imshow(np.ma.masked_equal(image, 0), origin="lower", extent=box, cmap="Blues", vmin=0, vmax=2, alpha=0.8)
    r_in = np.where(r_in > 0, r_in, np.nan)
    for r, colour, label in ((r_out, "tab:blue", "outer envelope"), (r_in, "tab:orange", "inner envelope")):
        ax.plot(r, z, color=colour, lw=1.5, label=label)
        ax.plot(-r, z, color=colour, lw=1.5)
    if datasheet is not None:
        _datasheet_marks(ax, datasheet)
    ax.axhline(0, color="0.4", lw=0.8)
    top = max(z.max(), datasheet["A"] / 1000 if datasheet else -math.inf) + 0.1
    ax.set_xlim(-r_out.max() - 0.1, r_out.max() + 0.1)
    ax.set_ylim(z.min() - 0.1, top)
    ax.set_xlabel("r: signed distance from the joint-1 axis (m)")
    ax.set_ylabel("z: height above the base (m)")
    ax.set_aspect("equal")
    ax.set_title(
        f"{chain.name}: {point_label} workspace, side view\n"
        f"volume {est:.3f} m$^3$ [{low:.3f}, {high:.3f}], h = {h * 1000:g} mm, {occ.n_samples:.2g} samples"
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1), fontsize=8)
    ax.grid(alpha=0.3)


def _datasheet_marks(ax, datasheet: dict) -> None:
    ds = {k: v / 1000 for k, v in datasheet.items() if k != "volume"}
    marks = {
        "A (height at home)": (0, ds["A"]),
        "B (top)": (0, ds["B"]),
        "C (shoulder)": (0, ds["C"]),
        "C+D (elbow)": (0, ds["C"] + ds["D"]),
        "G (reach at C)": (ds["G"], ds["C"]),
    }
    for i, (label, (r, zz)) in enumerate(marks.items()):
        ax.plot([r], [zz], marker="x^sDo"[i], ls="none", ms=8, label=f"datasheet {label}")
    ax.axhline(-ds["F"], color="tab:brown", ls="--", lw=1, label="datasheet -F (depth below the base)")


def _manipulability_view(ax, chain: Chain, dm: DexterityMap, name: str, point_label: str) -> None:
    """``dm``'s ``name`` statistic (``"mean"`` or ``"max"``) over the r-z plane on ``ax``."""
    nr, nz = dm.count.shape
    box = (0, nr * dm.h, dm.z_lower, dm.z_lower + nz * dm.h)
    data = getattr(dm, name)
    shown = ax.imshow(np.ma.masked_where(dm.count.T == 0, data.T), origin="lower", extent=box, cmap="viridis")
    ax.figure.colorbar(shown, ax=ax, label=f"{name} sqrt(det(J J$^T$)), 6 x n J (linear rows in m)")
    ax.set_xlabel("r: distance from the joint-1 axis (m)")
    ax.set_ylabel("z: height above the base (m)")
    ax.set_title(
        f"{chain.name}: {name} Yoshikawa manipulability\nbinned by {point_label} position, {dm.h * 1000:g} mm cells"
    )
    ax.set_aspect("equal")
    rows = np.flatnonzero(dm.count.any(0))
    ax.set_xlim(0, (np.flatnonzero(dm.count.any(1)).max() + 2) * dm.h)
    ax.set_ylim(dm.z_lower + (rows.min() - 2) * dm.h, dm.z_lower + (rows.max() + 3) * dm.h)
