"""Counter-based randomness of the reaching envs: every random number is a pure hash.

Every random number of environment ``i`` is a hash of ``(key_i, episode_i, index)``, where
``key_i`` comes from that environment's seed. So a batch of N environments seeded ``s, s+1,
..., s+N-1`` draws exactly the numbers of N single environments with those seeds, without a
Python loop and without a generator per environment.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["EPISODE_SALT", "GOLDEN", "MASK32", "MIX_MULTIPLIERS", "SEED_BOUND", "keys_from_seeds", "uniform"]

Tensor = torch.Tensor

#: Seeds are integers in ``[0, SEED_BOUND)``: the key hashes a seed's 64 bits.
SEED_BOUND = 2**64

#: the hash's numbers (:mod:`envs.compiled_step` restates the hash with them): 32 bits; MurmurHash3's
#: finaliser's two multipliers; the golden-ratio increment of SplitMix's streams; the episode's salt
MASK32, MIX_MULTIPLIERS, GOLDEN, EPISODE_SALT = 0xFFFFFFFF, (0x85EBCA6B, 0xC2B2AE35), 0x9E3779B9, 0x7F4A7C15


def _mul32_(x: Tensor, c: int) -> Tensor:
    """``x = (x * c) mod 2**32``, in place, for int64 ``x`` in ``[0, 2**32)`` and a constant
    ``c`` in ``[0, 2**32)``.

    ``c`` is used as its signed 32-bit equal (``c - 2**32`` from ``2**31`` up), which is the
    same modulo ``2**32`` and keeps ``|x * c| < 2**63``: no int64 overflow, two ops.
    """
    return x.mul_(c - 2**32 if c >= 2**31 else c).bitwise_and_(MASK32)


def _mix32(x: Tensor) -> Tensor:
    """MurmurHash3's 32-bit finaliser: a bijection of ``[0, 2**32)`` that mixes all bits.
    ``x`` is left alone; the rounds work in place on the new tensor (half the memory
    traffic of a new tensor per op, for the all-environment resets of large batches)."""
    x = x ^ (x >> 16)
    _mul32_(x, MIX_MULTIPLIERS[0]).bitwise_xor_(x >> 13)
    return _mul32_(x, MIX_MULTIPLIERS[1]).bitwise_xor_(x >> 16)


def keys_from_seeds(seeds, device=None) -> Tensor:
    """Integer seeds in ``[0, 2**64)`` (a sequence or array) -> ``(n,)`` int64 keys in ``[0, 2**32)``.

    Larger seeds raise ``ValueError`` rather than aliasing a smaller one (gymnasium accepts any
    non-negative int, but only 64 bits go into the key)."""
    s = np.asarray(seeds, dtype=object).reshape(-1)
    bad = [v for v in s.tolist() if not isinstance(v, (int, np.integer)) or isinstance(v, bool)
           or not 0 <= v < SEED_BOUND]
    if bad:
        raise ValueError(f"seed must be an integer in [0, 2**64) (one per environment), got {bad[:5]}")
    s = np.array([int(v) for v in s.tolist()], dtype=np.uint64)
    lo = torch.from_numpy((s & np.uint64(MASK32)).astype(np.int64)).to(device)
    hi = torch.from_numpy((s >> np.uint64(32)).astype(np.int64)).to(device)
    return _mix32(lo ^ _mix32(hi ^ GOLDEN))


def uniform(key: Tensor, episode: Tensor, start: int, count: int, dtype: torch.dtype) -> Tensor:
    """Counter-based uniform numbers in ``[0, 1)``: ``(n,)`` keys and episodes -> ``(n, count)``.

    Column ``j`` is the draw number ``start + j`` of that (key, episode): a pure function,
    so any subset of environments can be (re)drawn in any order with the same result.
    24 random bits each (resolution 6e-8). The stream of one (key, episode) is SplitMix's:
    the finaliser applied to a start point plus ``j`` times the golden-ratio increment.
    """
    base = _mix32(key ^ _mix32((episode & MASK32) ^ EPISODE_SALT))  # (n,) start point
    steps = torch.tensor([(j * GOLDEN) & MASK32 for j in range(start, start + count)], device=key.device)
    h = _mix32((base[:, None] + steps).bitwise_and_(MASK32))  # (n, count)
    return h.bitwise_right_shift_(8).to(dtype).mul_(2.0**-24)
