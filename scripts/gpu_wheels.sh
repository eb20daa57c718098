#!/usr/bin/env bash
# Wheels for the GPU machine (Python 3.12, CuPy, NumPy, SciPy, OpenCV, scikit-image, pytest, httpx; no web
# stack): what the strip tie points' tests and bench/strips.py import beyond those (Pillow too: workers.tiff_jpeg
# decodes with it; scikit-image brings one, this pins ours), at this checkout's versions,
# into .whl/ (git-ignored locally: `echo /.whl/ >> .git/info/exclude`), for scripts/gpu_check.sh. About 48 MB.
# The registry's pystac 1.15.2 wheel holds one module (seen 2026-12-04: rio-tiler, bench/strips.py's tile read-back,
# did not import there), so pystac comes at 1.14.3, whose wheel is whole; a wheel whose package has no __init__.py is refused.
set -euo pipefail
cd "$(dirname "$0")/.."
version() { .venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))"; }
packages=()
for name in affine annotated-types cachetools click-plugins cligj color-operations httpx2 morecantile numexpr pillow \
    pydantic pydantic-core pyproj rasterio rio-tiler typing-inspection; do
    packages+=("$name==$(version "$name")")
done
packages+=("pystac==1.14.3")
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
