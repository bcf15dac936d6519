"""The numba decorators of the compiled kernels (importing this module imports numba)."""

from __future__ import annotations

import numba

__all__ = ["inline", "jit", "jit_fused", "jit_nogil"]

#: a compiled kernel: cached on disk, numpy's float semantics (a division by 0 gives inf or nan, no exception)
jit = numba.njit(cache=True, error_model="numpy")
#: a compiled kernel that releases the GIL, so that threads can run it on parts of a batch at once
jit_nogil = numba.njit(cache=True, error_model="numpy", nogil=True)
#: a compiled helper inlined into its callers (no call overhead in the hot loops)
inline = numba.njit(cache=True, error_model="numpy", inline="always")
#: :data:`jit_nogil` whose products and sums may fuse into FMA instructions (float64 results change in
#: their last bits; numba applies the flag to the kernels it inlines and calls, so only for code whose
#: results are not held bit for bit to another backend's)
jit_fused = numba.njit(cache=True, error_model="numpy", nogil=True, fastmath={"contract"})
