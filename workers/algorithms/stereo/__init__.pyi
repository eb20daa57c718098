"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.stereo``."""

from .dsm import (
    FILLED as FILLED,
)
from .dsm import (
    MEASURED as MEASURED,
)
from .dsm import (
    NO_DATA as NO_DATA,
)
from .dsm import (
    Dsm as Dsm,
)
from .dsm import (
    grid_dsm as grid_dsm,
)
from .frame_pairs import (
    PosedPair as PosedPair,
)
from .frame_pairs import (
    ground_samples as ground_samples,
)
from .frame_pairs import (
    neighbour_pairs as neighbour_pairs,
)
from .frame_pairs import (
    overlap_share as overlap_share,
)
from .frame_pairs import (
    posed_pair as posed_pair,
)
from .frame_pairs import (
    reduced_view as reduced_view,
)
from .frame_pairs import (
    view_counts as view_counts,
)
from .radiometry import (
    grey8 as grey8,
)
from .radiometry import (
    same_channels as same_channels,
)
from .radiometry import (
    to_8bit_pair as to_8bit_pair,
)
from .rectification import (
    Rectification as Rectification,
)
from .rectification import (
    affine_rectification as affine_rectification,
)
from .rectification import (
    disparity_range as disparity_range,
)
from .rectification import (
    fundamental_from_matches as fundamental_from_matches,
)
from .rectification import (
    identity_rectification as identity_rectification,
)
from .rectification import (
    rectified_fundamental as rectified_fundamental,
)
from .rectification import (
    remap_pair as remap_pair,
)
from .rectification import (
    rig_rectification as rig_rectification,
)
from .rectification import (
    sparse_matches as sparse_matches,
)
from .rectification import (
    uncalibrated_rectification as uncalibrated_rectification,
)
from .rectification import (
    warp_pair as warp_pair,
)
from .relief import (
    DISPARITY as DISPARITY,
)
from .relief import (
    TERRAIN as TERRAIN,
)
from .relief import (
    colour_ramp as colour_ramp,
)
from .relief import (
    hillshade as hillshade,
)
from .relief import (
    legend as legend,
)
from .relief import (
    shaded_relief as shaded_relief,
)
from .relief import (
    value_range as value_range,
)
from .rpc import (
    Rpc as Rpc,
)
from .rpc import (
    fit_rpc as fit_rpc,
)
from .rpc import (
    ground_sample_distance as ground_sample_distance,
)
from .satellite import (
    Correspondences as Correspondences,
)
from .satellite import (
    height_disparity_range as height_disparity_range,
)
from .satellite import (
    rectified_disparities as rectified_disparities,
)
from .satellite import (
    rpc_correspondences as rpc_correspondences,
)
from .satellite import (
    rpc_rectification as rpc_rectification,
)
from .satellite import (
    triangulate_rpc as triangulate_rpc,
)
