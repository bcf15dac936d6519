import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402
import torch  # noqa: E402

from iiwa_torch import compiled  # noqa: E402
from iiwa_torch.so3 import exp  # noqa: E402


@pytest.fixture(params=["compiled", "numpy"])
def small_kernel(request, monkeypatch):
    """What runs a small-batch closed form: the compiled kernel (numba; skipped without it), or the
    numpy code it restates (``compiled.ENABLED`` patched off)."""
    if request.param == "compiled" and not compiled.ENABLED:
        pytest.skip("numba not installed or IIWA_TORCH_NUMBA=0")
    if request.param == "numpy":
        monkeypatch.setattr(compiled, "ENABLED", False)
    return request.param


def placed(chain):
    """``chain`` given a base and a tool (a rotation and an offset each), in place; returns it."""
    base, tool = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    base[:3, :3] = exp(torch.tensor([0.1, -0.3, 0.7], dtype=torch.float64))
    base[:3, 3] = torch.tensor([0.2, -0.1, 0.05])
    tool[:3, :3] = exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    tool[:3, 3] = torch.tensor([0.02, -0.01, 0.1])
    chain.base.copy_(base)
    chain.tool.copy_(tool)
    return chain
