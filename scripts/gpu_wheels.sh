#!/usr/bin/env bash
# Wheels for the GPU machine (Python 3.12, CuPy, NumPy, SciPy, OpenCV, scikit-image, pytest, httpx; no web
# stack): what the strip tie points' tests and bench/strips.py import beyond those (Pillow too: workers.tiff_jpeg
# decodes with it; scikit-image brings one, this pins ours), at this checkout's versions,
# into .whl/ (git-ignored), for scripts/gpu_check.sh.
# The registry's pystac 1.15.2 wheel holds one module (seen 2026-12-04: rio-tiler, bench/strips.py's tile read-back,
# did not import there), so pystac comes at 1.14.3, whose wheel is whole; a wheel whose package has no __init__.py is refused.
#
#     bash scripts/gpu_wheels.sh          # every step's (tests ties kernels strips), about 57 MB
#     bash scripts/gpu_wheels.sh mosaic   # gpu_check.sh's mosaic step: the drone mosaic pipeline's wheels only
#                                         # (48 MB) and the bench's photos in .bench-data/ (8 MB, git-ignored), which
#                                         # with the tree (4 MB) fit a device run's 64 MiB, carry [".whl", ".bench-data"]
#
# The mosaic step's photos: budapest1-6 as they are, and the Brighton strip's six 4000 x 2250 photos (18 MB: with
# the wheels over the 64 MiB) shrunk to 2048 px, the bench's working size, their EXIF kept
# (drone_brighton_strip1_2048): both sides of the bench decode the same smaller files.
set -euo pipefail
cd "$(dirname "$0")/.."
version() { .venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))"; }
names=(affine annotated-types attrs certifi click click-plugins cligj pydantic pydantic-core pyproj rasterio
    threadpoolctl typing-inspection)  # pyproj: a job with GPS (workers.algorithms.geometry.geodesy), tests/scenes.py
set_name=${1:-all}
packages=()
if [[ $set_name != mosaic ]]; then
    names+=(cachetools color-operations httpx2 morecantile numexpr pillow rio-tiler)
    packages+=("pystac==1.14.3")
fi
for name in "${names[@]}"; do
    packages+=("$name==$(version "$name")")
done
rm -rf .whl  # the set asked for, not what an earlier call left
if [[ $set_name == mosaic ]]; then
    rm -rf .bench-data && mkdir .bench-data
    cp -r ../shared/data/stitching .bench-data/ && chmod -R u+w .bench-data  # (the shared copy is read-only)
    .venv/bin/python - ../shared/data/drone_brighton_strip1 .bench-data/drone_brighton_strip1_2048 <<'SHRINK'
import sys
from pathlib import Path

from PIL import Image

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
dst.mkdir()
for path in sorted(src.glob("*.JPG")):
    with Image.open(path) as photo:
        scale = 2048 / max(photo.size)
        small = photo.resize((round(photo.width * scale), round(photo.height * scale)), Image.Resampling.LANCZOS)
        small.save(dst / path.name, quality=95, exif=photo.info["exif"])
SHRINK
fi
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64 any; do
    platforms+=(--platform "$p")
done
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
    -d .whl "${packages[@]}"
python3 - .whl/*.whl <<'CHECK'
import sys, zipfile
for path in sys.argv[1:]:
    names = set(zipfile.ZipFile(path).namelist())
    tops = {n.split("/")[0] for n in names if "/" in n and ".dist-info/" not in n and ".data/" not in n}
    broken = sorted(t for t in tops if not t.endswith(".libs") and f"{t}/__init__.py" not in names)
    if broken:
        sys.exit(f"{path}: no __init__.py in {', '.join(broken)}: a broken wheel")
CHECK
