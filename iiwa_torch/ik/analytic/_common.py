"""Shared pieces of the closed-form solvers: result type, guarded trigonometry, structure
checks, the spherical-joint decomposition and joint-limit bookkeeping.

Guarded trigonometry: ``acos`` is ``atan2(+-s, c)`` with ``c`` clamped to ``[-1, 1]`` and ``s``
floored at ``TINY`` under the root; an ``atan2(y, x)`` whose arguments may both vanish has ``x``
set to 1 there. Values and gradients stay finite everywhere (also in unreachable branches): an
infinite derivative in a masked-out branch would otherwise give NaN through ``0 * inf``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import weakref
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch

from ...chain import Chain
from ...checks import check_finite, check_float_tensor, check_instance
from ...collision import Capsules, World, check_world, clearance
from ...dh import Convention, DHChain
from ...kinematics import untracked_cpu
from ...so3 import check_rigid
from ..limits import shift_into_limits

Tensor = torch.Tensor

IDEAL_TOL = 1e-6  # how far (m, rad) a DH row may miss its closed form's zeros; float32 holds cos(pi/2) = -4e-8
TINY = 1e-30  # floor under squared norms before a sqrt / atan2: sqrt(TINY) = 1e-15
_TWO_PI = 2 * math.pi


@dataclass(frozen=True)
class AnalyticSolutions:
    """Every branch of a closed-form IK, for a batch of targets with leading shape ``(...)``.

    Attributes:
        q: ``(..., B, n)`` joint angles (radians) of the ``B`` branches (a view with each
            joint's values contiguous in memory; ``.contiguous()`` it if needed), each joint wrapped
            into its limits when a turn of 2 pi gets it there (else into ``[-pi, pi]``).
            Always finite; meaningful only where ``reachable``.
        valid: ``(..., B)`` bool, ``reachable & within_limits``.
        reachable: ``(..., B)`` bool, the branch exists geometrically (the target is in reach).
        within_limits: ``(..., B)`` bool, every joint of ``q`` lies within the chain's limits.
        clearance: ``(..., B)`` minimum signed clearance of each branch (metres,
            :func:`iiwa_torch.collision.clearance`) when a world was given, else None.
        collision_free: ``(..., B)`` bool, ``clearance >= margin`` when a world was given (then
            ``valid`` requires it too), else None.
    """

    q: Tensor
    valid: Tensor
    reachable: Tensor
    within_limits: Tensor
    clearance: Tensor | None = None
    collision_free: Tensor | None = None


# ---------------------------------------------------------------- array libraries
# The closed forms are written once over the functions they take from ``TORCH`` (batched,
# differentiable) or ``NUMPY`` (CPU arrays: for a few poses, where a torch op's overhead
# dominates). Operators and indexing are the arrays' own; ``tensor`` turns a result into torch.
TORCH = SimpleNamespace(
    atan2=torch.atan2,
    cos=torch.cos,
    sin=torch.sin,
    sqrt=torch.sqrt,
    where=torch.where,
    rint=torch.round,  # half to even, as np.rint
    clamp_min=torch.clamp_min,
    clamp=torch.clamp,
    maximum=torch.maximum,
    logical_and=torch.logical_and,
    stack=torch.stack,
    cat=torch.cat,
    full_like=torch.full_like,
    moveaxis=torch.movedim,
    broadcast_shapes=torch.broadcast_shapes,
    tensor=lambda x: x,
    stack_full=lambda xs, shape: torch.stack([x.expand(shape) for x in xs]),
    swap=lambda x: x.transpose(-1, -2),
    front=lambda m: m.movedim((-2, -1), (0, 1)).contiguous(),  # (..., r, c) -> (r, c, ...)
    signs=lambda like: torch.tensor([1.0, -1.0], dtype=like.dtype, device=like.device),
    arange=lambda n, like: torch.arange(n, dtype=like.dtype, device=like.device),
    linspace=lambda a, b, n, like: torch.linspace(a, b, n, dtype=like.dtype, device=like.device),
    rows=lambda n, like: torch.arange(n, device=like.device),
    expand=lambda x, shape: x.expand(shape),
    unravel=torch.unravel_index,
    take=lambda x, index: x.gather(-1, index[:, None]).squeeze(-1),  # x[i, index[i]]
    nonzero=lambda mask: mask.nonzero().squeeze(-1),  # of a 1-D mask
    put=lambda x, index, values: x.index_put((index,), values),  # x with x[index] = values
    as_float=lambda mask, like: mask.to(like.dtype),
    rounded=lambda x, dtype: x,  # already computed in dtype
)
NUMPY = SimpleNamespace(
    atan2=np.arctan2,
    cos=np.cos,
    sin=np.sin,
    sqrt=np.sqrt,
    where=np.where,
    rint=np.rint,
    clamp_min=np.maximum,
    clamp=lambda x, lo, hi: np.minimum(np.maximum(x, lo), hi),  # np.clip's wrapper costs more on tiny arrays
    maximum=np.maximum,
    logical_and=np.logical_and,
    stack=np.stack,
    cat=np.concatenate,
    full_like=np.full_like,
    moveaxis=np.moveaxis,
    broadcast_shapes=np.broadcast_shapes,
    tensor=torch.from_numpy,
    stack_full=lambda xs, shape: _stack_full(xs, shape),
    swap=lambda x: np.swapaxes(x, -1, -2),
    front=lambda m: np.moveaxis(m, (-2, -1), (0, 1)),
    signs=lambda like: _SIGNS.astype(like.dtype, copy=False),
    arange=lambda n, like: np.arange(n, dtype=np.float64),
    linspace=lambda a, b, n, like: np.linspace(a, b, n),
    rows=lambda n, like: np.arange(n),
    expand=np.broadcast_to,
    unravel=np.unravel_index,
    take=lambda x, index: np.take_along_axis(x, index[:, None], -1)[:, 0],
    nonzero=np.flatnonzero,
    put=lambda x, index, values: _put(x.copy(), index, values),
    as_float=lambda mask, like: mask,  # bool times float is float64
    rounded=lambda x, dtype: x.astype(np.float32) if dtype == torch.float32 else x,  # as torch would hold it
)


_SIGNS = np.array([1.0, -1.0])
_SIGNS.flags.writeable = False


def _stack_full(xs: list[np.ndarray], shape: tuple) -> np.ndarray:
    """``(len(xs), *shape)``: the arrays ``xs`` broadcast to ``shape`` and stacked (filled in place:
    cheaper than ``np.stack`` of ``np.broadcast_to`` views)."""
    out = np.empty((len(xs), *shape), dtype=np.result_type(*xs))
    for i, x in enumerate(xs):
        out[i] = x
    return out


def _put(x: np.ndarray, index, values) -> np.ndarray:
    x[index] = values
    return x


# ---------------------------------------------------------------- guarded trigonometry
def safe_atan2(y: Tensor, x: Tensor, ops=TORCH) -> Tensor:
    """``atan2(y, x)``, 0 with a finite gradient where ``x`` and ``y`` both vanish (``ops``:
    :data:`TORCH` or :data:`NUMPY`, the arrays' library)."""
    degenerate = x * x + y * y < TINY
    return ops.atan2(y, ops.where(degenerate, 1.0, x))


def safe_norm2(x: Tensor, y: Tensor, ops=TORCH) -> Tensor:
    """``sqrt(x^2 + y^2)``, at least ``1e-15``, so its gradient stays finite at 0."""
    return ops.sqrt(ops.clamp_min(x * x + y * y, TINY))


def acos_pair(c: Tensor, tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """For a cosine ``c``: ``(cos, |sin|, ok)`` with ``cos`` clamped into ``[-1, 1]``,
    ``|sin| = sqrt(1 - cos^2)`` (guarded) and ``ok = |c| <= 1 + tol``.

    The angle of the branch with sign ``s`` is ``atan2(s * |sin|, cos)``.
    """
    ok = c.abs() <= 1 + tol
    cc = c.clamp(-1.0, 1.0)
    return cc, (1 - cc * cc).clamp_min(TINY).sqrt(), ok


def triangle(dist: Tensor, l1: float, l2: float, tol: float, ops=TORCH) -> tuple[Tensor, Tensor, Tensor]:
    """The angle between two links ``l1, l2`` whose free ends are ``dist`` apart (law of
    cosines): ``(cos, |sin|, ok)``, ``cos = (dist^2 - l1^2 - l2^2) / (2 l1 l2)`` clamped.

    ``|sin|`` comes from the factored form ``(l1 + l2 - d)(l1 + l2 + d)(d - |l1 - l2|)(d + |l1 - l2|)
    = (2 l1 l2 sin)^2``, not from ``1 - cos^2``: near the stretched or folded arm that keeps
    its relative accuracy (``sqrt(1 - cos^2)`` loses half the digits, 3e-4 m in float32).
    """
    c = (dist * dist - (l1 * l1 + l2 * l2)) / (2 * l1 * l2)
    ok = abs(c) <= 1 + tol
    outer, inner = l1 + l2, abs(l1 - l2)
    s2 = (outer - dist) * (outer + dist) * (dist - inner) * (dist + inner)
    return ops.clamp(c, -1.0, 1.0), ops.sqrt(ops.clamp_min(s2, TINY)) / (2 * l1 * l2), ok


def reach_tol(dtype: torch.dtype) -> float:
    """Slack on a cosine before a target counts as out of reach (rounding of ``|c| = 1``)."""
    return 1e-12 if dtype == torch.float64 else 1e-5


# ---------------------------------------------------------------- rotations
def zxzx(a: Tensor, b: Tensor, sig_a: float, sig_b: float, ops=TORCH) -> list[list]:
    """Entries ``A[i][k]`` of ``A = Rz(a) Rx(alpha_a) Rz(b) Rx(alpha_b)`` for ``sin(alpha) =
    sig_a, sig_b = +-1``, broadcast from ``a, b (...)`` (a structural zero is 0.0). Separate
    contiguous arrays: a product is a few elementwise kernels, no batched 3x3 product."""
    ca, sa, cb, sb = ops.cos(a), ops.sin(a), ops.cos(b), ops.sin(b)
    k = sig_a * sig_b
    return [
        [ca * cb, k * sa, sig_b * ca * sb],
        [sa * cb, -k * ca, sig_b * sa * sb],
        [sig_a * sb, 0.0, -k * cb],
    ]


def transpose_times(a: list[list], b: list[list]) -> list[list]:
    """Entries of ``A^T B`` for entries ``a`` (3 x 3) and ``b`` (3 x m), skipping zeros."""
    def entry(i: int, j: int):
        terms = [a[k][i] * b[k][j] for k in range(3) if not (isinstance(a[k][i], float) and a[k][i] == 0.0)]
        return functools.reduce(operator.add, terms)

    return [[entry(i, j) for j in range(len(b[0]))] for i in range(3)]


def entries(m: Tensor, ops=TORCH) -> list[list]:
    """``m (..., 3, c)`` -> its entries ``(3 x c)``, each a ``(...)`` array (contiguous tensors)."""
    r = ops.front(m)
    return [[r[k, j] for j in range(r.shape[1])] for k in range(3)]


def decompose_zxzxz(m: list[list], sig_a: float, sig_b: float, ops=TORCH) -> tuple[Tensor, Tensor, Tensor]:
    """All angles of ``M = Rz(a) Rx(alpha_a) Rz(b) Rx(alpha_b) Rz(c)`` for twists with
    ``sin(alpha) = sig_a, sig_b = +-1``: a spherical joint triple (shoulder or wrist).

    ``m``: the entries ``(3 x 2)`` of columns 0 and 2 of ``M``, each ``(...)`` -> ``a, b, c``,
    each ``(..., 2)``: branch 0 has ``sin(b) >= 0``, branch 1 is ``(a + pi, -b, c + pi)`` (not
    wrapped). ``c`` is taken from what is left once ``a, b`` are fixed, so the triple reproduces
    ``M`` also at ``sin b = 0`` (only ``a +- c`` determined there; ``a`` set to 0).
    """
    (m00, m02), (m10, m12), (m20, m22) = m
    sb = safe_norm2(m02, m12, ops)  # sin b >= 0
    cb = -sig_a * sig_b * m22
    b = ops.atan2(sb, cb)
    a = safe_atan2(sig_b * m12, sig_b * m02, ops)
    ca, sa = ops.cos(a), ops.sin(a)
    # First column of Rz(c) = (Rz(a) Rx(alpha_a) Rz(b) Rx(alpha_b))^T M e_x.
    cos_c = cb * (ca * m00 + sa * m10) + sig_a * sb * m20
    sin_c = sig_a * sig_b * (sa * m00 - ca * m10)
    c = safe_atan2(sin_c, cos_c, ops)
    return ops.stack([a, a + math.pi], -1), ops.stack([b, -b], -1), ops.stack([c, c + math.pi], -1)


# ---------------------------------------------------------------- chain structure
def _check_dh(chain, robot: str) -> None:
    check_instance(chain, Chain, "chain")
    if not isinstance(chain, DHChain):
        raise ValueError(f"the {robot} closed form solves the DH chains of its structure; {chain.name!r} is a "
                         f"{type(chain).__name__} (from a URDF?), for which ik.solve (the gradient IK) works")


def check_chain(chain: DHChain, n: int, rows: list[dict], robot: str) -> list[tuple[float, float, float, float]]:
    """Check that ``chain`` is a standard-DH chain of ``n`` joints whose rows obey ``rows``.

    Each dict may pin ``a``, ``d`` to 0 (``"a0"``, ``"d0"``), require a twist of
    ``+-pi/2`` (``"perp"``) or 0 (``"twist0"``), or a positive ``d``/``a`` (``"d+"``, ``"a+"``).
    Returns the rows ``(a, alpha, d, offset)`` as floats; raises ``ValueError`` otherwise.
    """
    _check_dh(chain, robot)
    if chain.convention is not Convention.STANDARD:
        raise ValueError(f"the {robot} closed form needs a standard-DH chain, got {chain.convention.value!r}")
    if chain.n_joints != n:
        raise ValueError(
            f"the {robot} closed form needs a chain of {n} joints, got {chain.name!r} with {chain.n_joints}"
        )
    table = [tuple(float(v) for v in row) for row in chain.dh.tolist()]
    eps = IDEAL_TOL
    for i, ((a, alpha, d, _), rule) in enumerate(zip(table, rows)):
        broken = {
            "a0": (abs(a) > eps, f"a = 0 (got {a:g})"),
            "d0": (abs(d) > eps, f"d = 0 (got {d:g})"),
            "a+": (a <= eps, f"a > 0 (got {a:g})"),
            "d+": (d <= eps, f"d > 0 (got {d:g})"),
            "perp": (abs(math.cos(alpha)) > eps, f"alpha = +-pi/2 (got {alpha:g})"),
            "twist0": (abs(alpha) > eps, f"alpha = 0 (got {alpha:g})"),
        }
        problems = [text for key, (bad, text) in broken.items() if rule.get(key) and bad]
        if problems:
            raise ValueError(
                f"chain {chain.name!r} does not have the {robot} structure: row {i + 1} needs "
                + ", ".join(problems)
            )
    return table


def sigma(alpha: float) -> float:
    """``sin(alpha)`` rounded to +-1 for a twist of +-pi/2."""
    return 1.0 if math.sin(alpha) > 0 else -1.0


def as_values(value, name: str, dtype: torch.dtype, device: torch.device, batch: tuple | None = None) -> Tensor:
    """``value``, a number, a sequence or a float32/float64 tensor, as a finite tensor of
    ``dtype`` on ``device``; with ``batch``, its shape must broadcast with it."""
    if isinstance(value, Tensor):
        check_float_tensor(value, name, "(...)")
        check_finite(value, name)
        t = value.to(device, dtype)
    else:
        try:
            t = torch.as_tensor(value, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name} must be a number or a float tensor, got {value!r:.60}") from None
        check_finite(t, name)
    if batch is not None:
        try:
            torch.broadcast_shapes(t.shape, batch)
        except RuntimeError:
            raise ValueError(f"{name} of shape {tuple(t.shape)} does not broadcast with the batch {batch}") from None
    return t


def check_target(chain: DHChain, target: Tensor) -> None:
    _check_dh(chain, "analytic")
    check_rigid(target, "target")
    dh = chain.dh
    if not (target.is_cpu and dh.is_cpu) and target.device != dh.device:  # is_cpu: no device objects built
        raise ValueError(f"target is on {target.device} but the chain is on {dh.device}")


def last_frame_target(chain: DHChain, target: Tensor) -> Tensor:
    """``(..., 4, 4)``: the target as ``T_0,n-1 Rz(theta_n)`` (base, tool and the last row's
    ``Tz(d_n) Tx(a_n) Rx(alpha_n)`` stripped): its origin is frame ``n - 1``'s (a wrist centre)."""
    flange_inv, base_inv = strip_transforms(chain)
    if base_inv is not None:
        target = base_inv.to(target.dtype) @ target
    return target @ flange_inv.to(target.dtype)


def strip_transforms(chain: DHChain) -> tuple[Tensor, Tensor | None]:
    """What :func:`last_frame_target` multiplies a target by, in the chain's dtype: ``(F, B)``,
    ``F (4, 4)`` the inverse of the last row's constant part times the tool (on the right),
    ``B (4, 4)`` the inverse of the base (on the left; None for the identity)."""
    a, alpha, d, _ = chain.dh[-1].tolist()
    ca, sa = math.cos(alpha), math.sin(alpha)
    last = torch.tensor([[1.0, 0, 0, a], [0, ca, -sa, 0], [0, sa, ca, d], [0, 0, 0, 1]], dtype=torch.float64)
    flange_inv = torch.linalg.inv(last.to(chain.tool) @ chain.tool)
    if torch.equal(chain.base, torch.eye(4, dtype=chain.base.dtype, device=chain.base.device)):
        return flange_inv, None
    return flange_inv, torch.linalg.inv(chain.base)


_NUMPY_STRIPS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain.geometry(float64) -> (F, B)


def numpy_strips(chain: DHChain) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`strip_transforms` as float64 numpy arrays, cached per chain geometry (rebuilt when the
    chain's buffers change)."""
    key = chain.geometry(torch.float64)
    strips = _NUMPY_STRIPS.get(key)
    if strips is None:
        strips = tuple(None if t is None else t.double().numpy() for t in strip_transforms(chain))
        _NUMPY_STRIPS[key] = strips
    return strips


def last_frame_numpy(chain: DHChain, target: np.ndarray, strips: tuple | None = None) -> np.ndarray:
    """:func:`last_frame_target` of a numpy ``target (..., 4, 4)``, in its dtype, by ``strips`` (default
    :func:`numpy_strips` of ``chain``; a caller that holds them saves the lookup)."""
    flange_inv, base_inv = numpy_strips(chain) if strips is None else strips
    if target.dtype != np.float64:
        flange_inv, base_inv = (None if t is None else t.astype(target.dtype) for t in (flange_inv, base_inv))
    return (target if base_inv is None else base_inv @ target) @ flange_inv


def numpy_applies(chain: DHChain, size: int, limit: int, *tensors: Tensor) -> bool:
    """Whether a closed form takes its numpy path: ``1..limit`` poses, and ``tensors`` and the
    chain's base and tool on the CPU with nothing to differentiate
    (:func:`~iiwa_torch.kinematics.untracked_cpu`)."""
    return 1 <= size <= limit and all(untracked_cpu(t) for t in (chain.base, chain.tool, *tensors))


# ---------------------------------------------------------------- joint limits
def joint_angles(chain: DHChain, thetas: list[Tensor], ops=TORCH) -> tuple[list[Tensor], Tensor]:
    """DH angles -> joint angles and whether all are within the limits (arrays of ``ops``).

    ``thetas``: one array per joint, broadcastable together (size 1 in a branch dim a joint does
    not depend on: wrapped once). Each loses its offset, is wrapped into ``[-pi, pi]``, then
    shifted by 2 pi where that gets it within its limits. Returns the joints and ``within``.
    """
    return wrap_joints(thetas, chain.dh[:, 3].tolist(), *chain.limits.tolist(), ops)


def wrap_joints(thetas: list, offsets: list, lows: list, highs: list, ops=TORCH) -> tuple[list, Tensor]:
    """:func:`joint_angles` for the chain's offsets and limits as lists of floats (rad), over the
    arrays of ``ops``."""
    qs, inside = [], []
    for theta, off, lo, hi in zip(thetas, offsets, lows, highs):
        q = theta - off if off else theta
        # into [-pi, pi] by rint, cheaper than remainder (the sweep's time: benchmarks/results/analytic.md)
        q = q - _TWO_PI * ops.rint(q * (1 / _TWO_PI))
        if hi > math.pi or lo < -math.pi:  # only then may a turn get q in [-pi, pi] inside
            q, fits = shift_into_limits(q, lo, hi)
        else:
            fits = (q >= lo) & (q <= hi)
        qs.append(q)
        inside.append(fits)
    return qs, reduce_grouped(ops.logical_and, inside)


def reduce_grouped(op, tensors: list[Tensor]) -> Tensor:
    """``op``-reduce broadcastable arrays, those of equal shape first: branch-independent
    joints are small, and broadcasting ops are the slow ones, so this saves full-size work."""
    groups: dict[tuple, Tensor] = {}
    for t in tensors:
        groups[t.shape] = op(groups[t.shape], t) if t.shape in groups else t
    return functools.reduce(op, sorted(groups.values(), key=lambda t: math.prod(t.shape)))


def finish(chain: DHChain, thetas: list[Tensor], reachable: Tensor, branch_dims: int, ops=TORCH) -> AnalyticSolutions:
    """DH angles (arrays of ``ops``) -> :class:`AnalyticSolutions` (torch): the joints and
    ``reachable`` broadcast to ``(..., b_1, ..., b_m)``, the last ``m = branch_dims`` dims the
    branch signs, flattened into ``q (..., B, n)``."""
    qs, within = joint_angles(chain, thetas, ops)
    shape = ops.broadcast_shapes(*(q.shape for q in qs), reachable.shape)
    batch, branches = tuple(shape[:-branch_dims]), math.prod(shape[-branch_dims:])
    # Joint-major memory (each joint's values contiguous, as chain.fk wants them): q is a
    # non-contiguous view; the branch dims flatten without a copy.
    q = ops.moveaxis(ops.stack_full(qs, shape), 0, -1).reshape(*batch, branches, len(qs))
    reachable, within = ops.stack_full([reachable, within], shape).reshape(2, *batch, branches)
    q, valid, reachable, within = (ops.tensor(x) for x in (q, reachable & within, reachable, within))
    return AnalyticSolutions(q=q, valid=valid, reachable=reachable, within_limits=within)


def with_clearance(chain: DHChain, sol: AnalyticSolutions, batch_ndim: int, world: World | None, margin: float,
                   capsules: Capsules | None) -> AnalyticSolutions:
    """``sol`` with every branch's clearance against ``world`` (``sol`` itself for ``None``). The
    world's batch shape broadcasts with the targets' ``(...)``, the first ``batch_ndim`` dims of
    ``sol.valid``; the branch dims after them are inserted into it."""
    check_world(world, margin, capsules)
    if world is None:
        return sol
    extra = sol.valid.ndim - batch_ndim
    local = world.map_batch(lambda t, k: t.reshape(*t.shape[: t.ndim - k], *(1,) * extra, *t.shape[t.ndim - k :]))
    clear = clearance(chain, sol.q, local, capsules)
    free = clear >= margin
    return dataclasses.replace(sol, valid=sol.valid & free, clearance=clear, collision_free=free)
