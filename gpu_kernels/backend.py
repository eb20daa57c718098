"""Array-module dispatch (the ``cupy.get_array_module`` idiom) with a guarded CuPy import.

The arrays decide the backend; the device is chosen once at a stage boundary with ``resolve_device``
and data moves there with ``to_device``, and back with ``to_host`` before anything is written.
"""

from __future__ import annotations

from functools import lru_cache
from types import ModuleType
from typing import Any, Literal

import numpy as np

Device = Literal["cpu", "cuda"]


@lru_cache(maxsize=1)
def _cupy() -> ModuleType | None:
    try:
        import cupy  # noqa: PLC0415 - optional dependency, only where a GPU stack is installed

        if cupy.cuda.runtime.getDeviceCount() < 1:
            return None
        return cupy
    except Exception:  # ImportError, or CUDA present but no usable driver/device
        return None


def cuda_available() -> bool:
    """True when CuPy imports and sees at least one CUDA device."""
    return _cupy() is not None


def resolve_device(requested: str) -> Device:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cuda`` without a GPU is an error."""
    if requested == "cpu":
        return "cpu"
    if requested == "cuda":
        if not cuda_available():
            raise RuntimeError("device 'cuda' was requested but CuPy found no CUDA device")
        return "cuda"
    if requested == "auto":
        return "cuda" if cuda_available() else "cpu"
    raise ValueError(f"unknown device {requested!r}; expected auto, cpu or cuda")


def get_array_module(*arrays: Any) -> ModuleType:
    """``cupy`` if any argument is a CuPy array, else ``numpy``."""
    cp = _cupy()
    if cp is not None:
        return cp.get_array_module(*arrays)  # type: ignore[no-any-return]
    return np


def to_device(array: np.ndarray, device: Device) -> Any:
    """Move a host array to ``device`` (a no-op for ``cpu``)."""
    if device == "cpu":
        return array
    cp = _cupy()
    if cp is None:
        raise RuntimeError("no CUDA device to move data to")
    return cp.asarray(array)


def to_host(array: Any) -> np.ndarray:
    """A NumPy array of a CuPy array (copied to the host) or of anything NumPy takes (as is)."""
    if hasattr(array, "__cuda_array_interface__"):
        return array.get()  # type: ignore[no-any-return]
    return np.asarray(array)


def ndimage_module(xp: ModuleType) -> ModuleType:
    """``scipy.ndimage`` for NumPy arrays, ``cupyx.scipy.ndimage`` for CuPy arrays."""
    if xp is np:
        from scipy import ndimage  # noqa: PLC0415

        return ndimage
    from cupyx.scipy import ndimage as cupy_ndimage  # noqa: PLC0415 - only with CuPy present

    return cupy_ndimage  # type: ignore[no-any-return]
