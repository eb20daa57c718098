"""What stages, tests and benchmarks may import from ``workers.algorithms.strips``."""

from .coarse import (
    CoarseOptions as CoarseOptions,
)
from .coarse import (
    CoarseRegistration as CoarseRegistration,
)
from .coarse import (
    HarrisSetting as HarrisSetting,
)
from .coarse import (
    feasible_levels as feasible_levels,
)
from .coarse import (
    register_coarse as register_coarse,
)
from .fine import (
    FineOptions as FineOptions,
)
from .fine import (
    PairTies as PairTies,
)
from .fine import (
    TieFilter as TieFilter,
)
from .fine import (
    carry_ties as carry_ties,
)
from .fine import (
    filter_ties as filter_ties,
)
from .fine import (
    fine_tie_points as fine_tie_points,
)
from .homography import (
    refine_homography as refine_homography,
)
from .overlap import (
    along_strip as along_strip,
)
from .overlap import (
    distant_pairs as distant_pairs,
)
from .overlap import (
    overlap_box as overlap_box,
)
from .overlap import (
    overlap_polygon as overlap_polygon,
)
from .overlap import (
    spread_along as spread_along,
)
from .pyramid import (
    FramePyramid as FramePyramid,
)
from .pyramid import (
    build_pyramid as build_pyramid,
)
from .pyramid import (
    coarsest_level as coarsest_level,
)
from .sources import (
    Windowed as Windowed,
)
from .sources import (
    open_windows as open_windows,
)
from .sources import (
    read_pyramid as read_pyramid,
)
from .tracks import (
    DisjointSet as DisjointSet,
)
from .tracks import (
    Tracks as Tracks,
)
from .tracks import (
    build_tracks as build_tracks,
)
