"""The damped-least-squares (DLS) joint step, written once for the whole library:
``dq = J^T (J J^T + damping I)^-1 e`` (rad) for ``J (m, n)`` (m = 6 pose, 3 position) and ``e (m,)``.

``damping`` (the squared damping factor, units of ``J J^T``: m^2 for an arm) keeps ``dq`` finite
where ``J`` loses rank (Nakamura and Hanafusa; Wampler). :func:`dls_step` takes any batch shape;
:func:`dls_step_batch_last` is the gradient solver's batch-last layout (its solve
:func:`cholesky_solve_batch_last`), :func:`dls_step_numpy` the step for a few numpy problems.
"""

from __future__ import annotations

import numpy as np
import torch

from ..checks import all_finite, broadcast_shapes, check_finite, check_float_tensor, check_positive

__all__ = ["dls_step", "dls_step_batch_last", "dls_step_numpy", "cholesky_solve_batch_last"]

Tensor = torch.Tensor

_LAPACK_BATCH = 384  # up to this many problems, LAPACK's per-matrix Cholesky beats the unrolled one (paths.md)


def cholesky_solve_batch_last(A: Tensor, rhs: Tensor, floor: float) -> Tensor:
    """Solve ``A x = rhs`` for symmetric positive definite ``A (m, m, b)`` (lower triangle read),
    ``rhs (m, k, b)`` -> ``x (m, k, b)``, by Cholesky ``A = L L^T``: LAPACK per matrix for small
    batches, else written out entry by entry over the batch (fewer, larger kernels). Always
    finite: pivots are floored at ``floor``, and a matrix LAPACK finds not positive definite
    gives ``x = 0``. Differentiable."""
    if A.shape[2] <= _LAPACK_BATCH:
        lower = A.permute(2, 0, 1).tril()
        # symmetric from the lower triangle, so the gradient reaches every entry that was read
        L, info = torch.linalg.cholesky_ex(lower + lower.tril(-1).mT)
        x = torch.cholesky_solve(rhs.permute(2, 0, 1), L).permute(1, 2, 0)
        return torch.where(info == 0, x, 0.0)
    m = A.shape[0]
    L = [[None] * m for _ in range(m)]  # L[i][j], (b,) each
    inv = [None] * m  # 1 / L[j][j]
    for j in range(m):
        inv[j] = _minus_products(A[j, j], [(L[j][k], L[j][k]) for k in range(j)]).clamp_min(floor).rsqrt()
        for i in range(j + 1, m):
            L[i][j] = _minus_products(A[i, j], [(L[i][k], L[j][k]) for k in range(j)]) * inv[j]
    y = [None] * m  # L y = rhs
    for i in range(m):
        y[i] = _minus_products(rhs[i], [(L[i][k], y[k]) for k in range(i)]) * inv[i]
    x = [None] * m  # L^T x = y
    for i in reversed(range(m)):
        x[i] = _minus_products(y[i], [(L[k][i], x[k]) for k in range(i + 1, m)]) * inv[i]
    return torch.stack(x)


def _minus_products(x: Tensor, pairs: list[tuple[Tensor, Tensor]]) -> Tensor:
    """``x - sum(a * b for a, b in pairs)``, one fused ``addcmul`` per pair."""
    for a, b in pairs:
        x = torch.addcmul(x, a, b, value=-1)
    return x


def dls_step_batch_last(J: Tensor, rhs: Tensor, damping: Tensor, floor: float, free: Tensor | None = None) -> Tensor:
    """``J^T (J J^T + damping I)^-1 rhs`` for ``J (m, n, b)``, ``rhs (m, k, b)`` (k right-hand
    sides), ``damping (b,)`` -> ``(n, k, b)``; Cholesky pivots floored at ``floor``. With
    ``free (n, b)`` (0 or 1), the other columns of ``J`` count as zero (those joints stay put)."""
    m = J.shape[0]
    A = J.new_empty(m, m, J.shape[2])
    for r in range(m):
        A[r:, r] = ((J[r] if free is None else J[r] * free) * J[r:]).sum(1)
    A.diagonal(0, 0, 1).add_(damping[:, None])
    y = cholesky_solve_batch_last(A, rhs, floor)
    dq = (J[:, :, None] * y[:, None]).sum(0)
    return dq if free is None else dq * free[:, None]


def dls_step_numpy(jacobian: np.ndarray, error: np.ndarray, damping: np.ndarray, free: np.ndarray | None = None
                   ) -> np.ndarray:
    """:func:`dls_step` on numpy arrays, unchecked (a numpy op costs a fraction of a torch op):
    ``jacobian (..., m, n)``, ``error (..., m)``, ``damping`` broadcasting to ``(...)``, ``free``
    as in :func:`dls_step_batch_last` -> ``(..., n)``. LU, not Cholesky: the same step to rounding."""
    held = jacobian if free is None else jacobian * free[..., None, :]
    A = (held[..., :, None, :] * jacobian[..., None, :, :]).sum(-1) + np.asarray(damping)[..., None, None] * np.eye(
        jacobian.shape[-2])
    dq = (jacobian * np.linalg.solve(A, error[..., None])).sum(-2)
    return dq if free is None else dq * free


def dls_step(jacobian: Tensor, error: Tensor, damping: Tensor | float) -> Tensor:
    """The DLS joint step ``J^T (J J^T + damping I)^-1 e`` (rad), batched and differentiable.

    Args:
        jacobian: ``(..., m, n)``, m = 6 (pose: linear rows m/rad, then angular rows) or 3
            (position only); the rows may be weighted by the caller.
        error: ``(..., m)``, the error to remove, in the rows' units (m; rad for angular rows).
        damping: ``> 0``, a number or a tensor broadcasting to the batch ``(...)``, added to
            the diagonal of ``J J^T`` (the squared damping factor, m^2 for position rows).

    Returns:
        ``(..., n)`` joint step, rad. The batch shape is the broadcast of the three inputs'.
    """
    check_float_tensor(jacobian, "jacobian", "(..., m, n)")
    check_float_tensor(error, "error", "(..., m)")
    if jacobian.ndim < 2:
        raise ValueError(f"jacobian must have shape (..., m, n), got {tuple(jacobian.shape)}")
    m, n = jacobian.shape[-2:]
    if error.ndim == 0 or error.shape[-1] != m:
        raise ValueError(
            f"error must have shape (..., {m}) to match jacobian (..., {m}, {n}), got {tuple(error.shape)}"
        )
    if error.dtype != jacobian.dtype:
        raise TypeError(f"error must have jacobian's dtype {jacobian.dtype}, got {error.dtype}")
    check_finite(jacobian, "jacobian")
    check_finite(error, "error")
    if not isinstance(damping, Tensor):
        check_positive(damping, "damping")
    damping = torch.as_tensor(damping, dtype=jacobian.dtype, device=jacobian.device)
    if not all_finite(damping) or not bool((damping > 0).all()):
        raise ValueError("damping must be positive and finite")
    batches = {"jacobian's batch": jacobian.shape[:-2], "error's": error.shape[:-1], "damping's": damping.shape}
    batch = broadcast_shapes(batches)
    J = jacobian.expand(*batch, m, n).reshape(-1, m, n).permute(1, 2, 0)  # (m, n, b)
    e = error.expand(*batch, m).reshape(-1, m).T[:, None]  # (m, 1, b)
    lam = damping.expand(batch).reshape(-1)
    floor = torch.finfo(jacobian.dtype).tiny
    return dls_step_batch_last(J, e, lam, floor)[:, 0].T.reshape(*batch, n)
