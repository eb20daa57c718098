"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.mosaic``."""

from .alignment import (
    TiePoints as TiePoints,
)
from .alignment import (
    apply_homography as apply_homography,
)
from .alignment import (
    chain_homographies as chain_homographies,
)
from .alignment import (
    corner_sigmas as corner_sigmas,
)
from .alignment import (
    frame_corners as frame_corners,
)
from .alignment import (
    is_plausible as is_plausible,
)
from .alignment import (
    level_plane as level_plane,
)
from .alignment import (
    refine_homographies as refine_homographies,
)
from .alignment import (
    spanning_tree as spanning_tree,
)
from .alignment import (
    tie_residuals_px as tie_residuals_px,
)
from .alignment import (
    triple_overlap_share as triple_overlap_share,
)
from .blending import (
    feather_weights as feather_weights,
)
from .blending import (
    gain_compensation as gain_compensation,
)
from .blending import (
    overlap_statistics as overlap_statistics,
)
from .blending import (
    warp_maps as warp_maps,
)
from .ccd import (
    ccd_gains as ccd_gains,
)
from .ccd import (
    column_brightness as column_brightness,
)
from .compose import (
    compose_block as compose_block,
)
from .compose import (
    compose_block_multiband as compose_block_multiband,
)
from .compose import (
    gains_and_coverage as gains_and_coverage,
)
from .compose import (
    output_box as output_box,
)
from .features import (
    FlannIndex as FlannIndex,
)
from .features import (
    OverlapGuide as OverlapGuide,
)
from .features import (
    SearchIndex as SearchIndex,
)
from .features import (
    detect as detect,
)
from .features import (
    detect_sift as detect_sift,
)
from .features import (
    detector_name as detector_name,
)
from .features import (
    match as match,
)
from .features import (
    match_index as match_index,
)
from .features import (
    match_ratio as match_ratio,
)
from .features import (
    registration_copy as registration_copy,
)
from .features import (
    to_full_pixels as to_full_pixels,
)
from .grid import (
    MAX_OUTPUT_PIXELS as MAX_OUTPUT_PIXELS,
)
from .grid import (
    MIN_GPS_SPREAD_M as MIN_GPS_SPREAD_M,
)
from .grid import (
    disk_needed as disk_needed,
)
from .grid import (
    fit_plane_to_map as fit_plane_to_map,
)
from .grid import (
    map_grid as map_grid,
)
from .grid import (
    output_size_problem as output_size_problem,
)
from .grid import (
    photo_px_per_plane_px as photo_px_per_plane_px,
)
from .grid import (
    pixel_grid as pixel_grid,
)
from .grid import (
    polygon_area as polygon_area,
)
from .grid import (
    refine_grid as refine_grid,
)
from .homography import (
    estimate_fundamental as estimate_fundamental,
)
from .homography import (
    estimate_homography as estimate_homography,
)
from .homography import (
    spread_subset as spread_subset,
)
from .multiband import (
    SEAM_FRAME_PX as SEAM_FRAME_PX,
)
from .multiband import (
    blend_bands as blend_bands,
)
from .multiband import (
    label_window as label_window,
)
from .multiband import (
    margin_px as margin_px,
)
from .multiband import (
    owned_regions as owned_regions,
)
from .multiband import (
    seam_labels as seam_labels,
)
from .multiband import (
    seam_points as seam_points,
)
from .multiband import (
    seam_visibility as seam_visibility,
)
from .pairing import (
    candidate_pairs as candidate_pairs,
)
from .pairing import (
    local_metres as local_metres,
)
from .ties import (
    guided_tie_points as guided_tie_points,
)
from .ties import (
    overlap_share as overlap_share,
)
from .ties import (
    refine_tie_points as refine_tie_points,
)
from .ties import (
    refined_pair_ties as refined_pair_ties,
)
from .ties import (
    refit_homography as refit_homography,
)
from .ties import (
    tie_corners as tie_corners,
)
