"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.calibration``."""

from .board import (
    BoardViews as BoardViews,
)
from .board import (
    board_points as board_points,
)
from .board import (
    board_views as board_views,
)
from .board import (
    find_chessboard as find_chessboard,
)
from .board import (
    paired_points as paired_points,
)
from .board import (
    view_entry as view_entry,
)
from .intrinsics import (
    CalibrationResult as CalibrationResult,
)
from .intrinsics import (
    calibrate_camera as calibrate_camera,
)
from .limits import (
    MIN_POINTS as MIN_POINTS,
)
from .limits import (
    MIN_VIEWS as MIN_VIEWS,
)
from .plumb_line import (
    plumb_line as plumb_line,
)
from .stereo_calibration import (
    StereoCalibrationResult as StereoCalibrationResult,
)
from .stereo_calibration import (
    stereo_calibrate as stereo_calibrate,
)
from .stereo_rig import (
    StereoRig as StereoRig,
)
from .stereo_rig import (
    measure as measure,
)
from .stereo_rig import (
    triangulate_midpoint as triangulate_midpoint,
)
