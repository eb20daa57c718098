"""What stages, the API, tests and benchmarks may import from ``workers.algorithms.specimen``."""

from .mesh import (
    Mesh as Mesh,
)
from .mesh import (
    MeshFormatError as MeshFormatError,
)
from .mesh import (
    PlaneFrame as PlaneFrame,
)
from .mesh import (
    best_fit_plane as best_fit_plane,
)
from .mesh import (
    distance_to_surface as distance_to_surface,
)
from .mesh import (
    plane_through as plane_through,
)
from .mesh import (
    read_mesh as read_mesh,
)
from .resection import (
    Resection as Resection,
)
from .resection import (
    pose_from_json as pose_from_json,
)
from .resection import (
    pose_json as pose_json,
)
from .resection import (
    resect_plane as resect_plane,
)
from .resection import (
    resect_points as resect_points,
)
from .surface import (
    Surface as Surface,
)
from .surface import (
    compose_views as compose_views,
)
from .surface import (
    mesh_surface as mesh_surface,
)
from .surface import (
    photo_footprint as photo_footprint,
)
from .surface import (
    photo_sampling as photo_sampling,
)
from .surface import (
    plate_surface as plate_surface,
)
from .surface import (
    raster_shape as raster_shape,
)
from .surface import (
    resample_raster as resample_raster,
)
