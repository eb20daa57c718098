"""Aerial strips (long composite frames, a homography between neighbours): tie points as the source work
does them, coarse to fine. A coarse registration per pair on a pyramid level (Harris + NCC, RANSAC, the
spread criterion), fine tie points at native resolution read by window, and tracks over frames that overlap
more than once.

The names other packages may use are those of ``__init__.pyi``; they are imported lazily, on first
use (``lazy_loader``, as scikit-image does), so importing one light module never loads OpenCV.
"""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach_stub(__name__, __file__)
