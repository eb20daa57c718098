"""Every kernel test runs on NumPy, and again on CuPy where a CUDA device is present."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from gpu_kernels.backend import cuda_available, to_host


@pytest.fixture(params=["numpy", pytest.param("cupy", marks=pytest.mark.gpu)])
def xp(request: pytest.FixtureRequest) -> Any:
    if request.param == "numpy":
        return np
    if not cuda_available():
        pytest.skip("needs CuPy and a CUDA device")
    import cupy

    return cupy


host = to_host  # test modules import it from here
