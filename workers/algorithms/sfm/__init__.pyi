"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.sfm``."""

from .bundle import (
    BundleOptions as BundleOptions,
)
from .bundle import (
    BundleProblem as BundleProblem,
)
from .bundle import (
    adjust as adjust,
)
from .bundle import (
    refine_points as refine_points,
)
from .bundle import (
    reproject as reproject,
)
from .bundle import (
    rms as rms,
)
from .bundle import (
    robust_rho as robust_rho,
)
from .bundle import (
    triangulate_rays as triangulate_rays,
)
from .datum import (
    DATUMS as DATUMS,
)
from .datum import (
    GCP_ROLES as GCP_ROLES,
)
from .datum import (
    IMAGE_STATUSES as IMAGE_STATUSES,
)
from .datum import (
    Attitude as Attitude,
)
from .datum import (
    GpsFix as GpsFix,
)
from .datum import (
    line_similarity as line_similarity,
)
from .datum import (
    refine_similarity as refine_similarity,
)
from .datum import (
    rotation_from_attitude as rotation_from_attitude,
)
from .datum import (
    similarity_3d as similarity_3d,
)
from .gcp import (
    GCP_FILE_NAMES as GCP_FILE_NAMES,
)
from .gcp import (
    GroundControlPoint as GroundControlPoint,
)
from .gcp import (
    LocalFrame as LocalFrame,
)
from .gcp import (
    gcp_file_name as gcp_file_name,
)
from .gcp import (
    parse_gcp_file as parse_gcp_file,
)
from .gcp import (
    parse_gcp_list as parse_gcp_list,
)
from .gcp import (
    parse_opensfm_gcps as parse_opensfm_gcps,
)
from .gcp import (
    scale_observations as scale_observations,
)
from .ortho import (
    SURFACE_INTERPOLATED as SURFACE_INTERPOLATED,
)
from .ortho import (
    SURFACE_MEASURED as SURFACE_MEASURED,
)
from .ortho import (
    SURFACE_NO_DATA as SURFACE_NO_DATA,
)
from .ortho import (
    CellGrid as CellGrid,
)
from .ortho import (
    GroundSurface as GroundSurface,
)
from .ortho import (
    RasterGrid as RasterGrid,
)
from .ortho import (
    cell_medians as cell_medians,
)
from .ortho import (
    dense_grid as dense_grid,
)
from .ortho import (
    dense_surface as dense_surface,
)
from .ortho import (
    ground_crop as ground_crop,
)
from .ortho import (
    ground_surface as ground_surface,
)
from .ortho import (
    relief_maps as relief_maps,
)
from .ortho import (
    surface_raster as surface_raster,
)
from .reconstruction import (
    Reconstruction as Reconstruction,
)
from .reconstruction import (
    ReconstructionOptions as ReconstructionOptions,
)
from .reconstruction import (
    reconstruct as reconstruct,
)
from .tracks import (
    build_tracks as build_tracks,
)
from .tracks import (
    verify_pairs as verify_pairs,
)
