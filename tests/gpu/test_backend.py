"""Array-module dispatch; the CUDA half runs only where CuPy sees a GPU."""

from __future__ import annotations

import numpy as np
import pytest

from gpu_kernels.backend import cuda_available, get_array_module, resolve_device, to_device, to_host


def test_cpu_dispatch() -> None:
    a = np.arange(6.0)
    assert get_array_module(a) is np and to_host(to_device(a, "cpu")) is a
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if cuda_available() else "cpu")
    with pytest.raises(ValueError):
        resolve_device("tpu")


@pytest.mark.skipif(cuda_available(), reason="checks the error raised without a GPU")
def test_cuda_without_a_gpu_is_a_clear_error() -> None:
    with pytest.raises(RuntimeError, match="no CUDA device"):
        resolve_device("cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not cuda_available(), reason="needs CuPy and a CUDA device")
def test_round_trip_through_the_gpu() -> None:
    a = np.random.default_rng(0).random((64, 64)).astype(np.float32)
    on_gpu = to_device(a, "cuda")
    assert get_array_module(on_gpu).__name__ == "cupy"
    assert np.array_equal(to_host(on_gpu), a)
