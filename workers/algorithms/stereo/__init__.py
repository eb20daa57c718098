"""Elevation from stereo pairs: rectification (a calibrated rig, a fundamental matrix, or RPCs), RPC camera
models, triangulation of disparity maps, and gridding heights into a DSM with its relief rendering.

The names other packages may use are those of ``__init__.pyi``; they are imported lazily, on first
use (``lazy_loader``, as scikit-image does), so importing the package never loads OpenCV.
"""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach_stub(__name__, __file__)
