"""Disparity maps of stereo pairs: OpenCV's semi-global matcher and the source work's local method
(``gpu_kernels.stereo_local``), their shared checks and filling, and dense scoring.

The names other packages may use are those of ``__init__.pyi``; they are imported lazily, on first
use (``lazy_loader``, as scikit-image does), so importing the package never loads OpenCV.
"""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach_stub(__name__, __file__)
