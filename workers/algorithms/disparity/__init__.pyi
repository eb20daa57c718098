"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.disparity``."""

from .local import (
    grey as grey,
)
from .local import (
    local as local,
)
from .middlebury import (
    StereoPair as StereoPair,
)
from .middlebury import (
    read_pair as read_pair,
)
from .pair import (
    Method as Method,
)
from .pair import (
    match_pair as match_pair,
)
from .pair import (
    restrict as restrict,
)
from .postprocess import (
    Disparity as Disparity,
)
from .postprocess import (
    fill_background as fill_background,
)
from .postprocess import (
    left_right_check as left_right_check,
)
from .postprocess import (
    remove_speckles as remove_speckles,
)
from .scoring import (
    Score as Score,
)
from .scoring import (
    score_disparity as score_disparity,
)
from .sgbm import (
    REFERENCE as REFERENCE,
)
from .sgbm import (
    TUNED as TUNED,
)
from .sgbm import (
    SgbmParams as SgbmParams,
)
from .sgbm import (
    opencv_sgbm as opencv_sgbm,
)
from .sgbm import (
    sgbm as sgbm,
)
