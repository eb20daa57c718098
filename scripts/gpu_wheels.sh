#!/usr/bin/env bash
# Wheels for the GPU machine (Python 3.12, CuPy, NumPy, SciPy, OpenCV, scikit-image, pytest, httpx; no web
# stack): what the strip tie points' tests and bench/strips.py import beyond those (Pillow too: workers.tiff_jpeg
# decodes with it; scikit-image brings one, this pins ours), at this checkout's versions,
# into .whl/ (git-ignored locally: `echo /.whl/ >> .git/info/exclude`), for scripts/gpu_check.sh. About 48 MB.
# Seen 2026-12-04: the registry's pystac 1.15.2 wheel held one file, so rio-tiler (bench/strips.py's tile
# read-back) did not import there; the bench prints its other figures first.
set -euo pipefail
cd "$(dirname "$0")/.."
version() { .venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))"; }
packages=()
for name in affine annotated-types cachetools click-plugins cligj color-operations httpx2 morecantile numexpr pillow \
    pydantic pydantic-core pyproj pystac rasterio rio-tiler typing-inspection; do
    packages+=("$name==$(version "$name")")
done
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64 any; do
    platforms+=(--platform "$p")
done
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
    -d .whl "${packages[@]}"
