"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.geometry``."""

from .camera import (
    CONVENTIONS as CONVENTIONS,
)
from .camera import (
    DISTORTION_TERMS as DISTORTION_TERMS,
)
from .camera import (
    Camera as Camera,
)
from .camera import (
    Convention as Convention,
)
from .camera import (
    apply_brown as apply_brown,
)
from .geodesy import (
    FLIP_Y as FLIP_Y,
)
from .geodesy import (
    fit_similarity as fit_similarity,
)
from .geodesy import (
    lonlat_to_utm as lonlat_to_utm,
)
from .geodesy import (
    similarity_scale as similarity_scale,
)
from .geodesy import (
    utm_epsg as utm_epsg,
)
from .geodesy import (
    utm_to_lonlat as utm_to_lonlat,
)
from .rotation import (
    rotation_from_vector as rotation_from_vector,
)
from .rotation import (
    rotations_from_vectors as rotations_from_vectors,
)
from .rotation import (
    vector_from_rotation as vector_from_rotation,
)
from .rotation import (
    world_to_camera as world_to_camera,
)
