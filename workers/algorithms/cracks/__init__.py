"""Crack surveys' image analysis: the crack detector (features, network, detection), crack geometry
(skeletons, lengths, widths, matching between load steps), tiling of large rasters, evaluation.

The names other packages may use are those of ``__init__.pyi``; they are imported lazily, on first
use (``lazy_loader``, as scikit-image does), so importing one light module never loads OpenCV.
"""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach_stub(__name__, __file__)
