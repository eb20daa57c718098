"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.cracks``."""

from .detection import (
    crack_probability as crack_probability,
)
from .detection import (
    detect_cracks as detect_cracks,
)
from .detection import (
    features_probability as features_probability,
)
from .detection import (
    hysteresis_threshold as hysteresis_threshold,
)
from .detection import (
    remove_short_components as remove_short_components,
)
from .detection import (
    smallest_detectable_width as smallest_detectable_width,
)
from .evaluation import (
    ToleranceCounts as ToleranceCounts,
)
from .evaluation import (
    tolerance_counts as tolerance_counts,
)
from .features import (
    N_BANK as N_BANK,
)
from .features import (
    context_features as context_features,
)
from .features import (
    pixel_features as pixel_features,
)
from .features import (
    to_gray as to_gray,
)
from .geometry import (
    Crack as Crack,
)
from .geometry import (
    WidthEstimate as WidthEstimate,
)
from .geometry import (
    background_px as background_px,
)
from .geometry import (
    crack_coverage as crack_coverage,
)
from .geometry import (
    darkening as darkening,
)
from .geometry import (
    estimate_width as estimate_width,
)
from .geometry import (
    length_histogram as length_histogram,
)
from .geometry import (
    match_cracks as match_cracks,
)
from .geometry import (
    measure_cracks as measure_cracks,
)
from .geometry import (
    path_length as path_length,
)
from .geometry import (
    smooth_path as smooth_path,
)
from .geometry import (
    summarise_cracks as summarise_cracks,
)
from .network import (
    FEATURE_VERSION as FEATURE_VERSION,
)
from .network import (
    MODEL_FILE as MODEL_FILE,
)
from .network import (
    NET_LAYERS as NET_LAYERS,
)
from .network import (
    CrackModel as CrackModel,
)
from .network import (
    CrackNet as CrackNet,
)
from .network import (
    PixelMLP as PixelMLP,
)
from .network import (
    avg_pool2 as avg_pool2,
)
from .network import (
    conv2d as conv2d,
)
from .network import (
    load_crack_model as load_crack_model,
)
from .network import (
    upsample2 as upsample2,
)
from .profile import (
    ProfileFit as ProfileFit,
)
from .profile import (
    crack_widths as crack_widths,
)
from .profile import (
    fit_blurred_line as fit_blurred_line,
)
from .profile import (
    isotropic_sampling as isotropic_sampling,
)
from .profile import (
    line_like as line_like,
)
from .profile import (
    profile_widths as profile_widths,
)
from .profile import (
    reference_contrast as reference_contrast,
)
from .profile import (
    resolved as resolved,
)
from .profile import (
    sampling_across as sampling_across,
)
from .profile import (
    with_widths as with_widths,
)
from .skeleton import (
    thin as thin,
)
from .tiling import (
    map_in_tiles as map_in_tiles,
)
