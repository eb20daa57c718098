"""Planar mosaics: which frames to pair, features and descriptor matching, robust homographies, the
global alignment of frames, the output grid, gain compensation, blending and block composition.

The names other packages may use are those of ``__init__.pyi``; they are imported lazily, on first
use (``lazy_loader``, as scikit-image does), so importing one light module never loads OpenCV.
"""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach_stub(__name__, __file__)
