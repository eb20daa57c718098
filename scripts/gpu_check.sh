#!/usr/bin/env bash
# The GPU checks in one run, on a machine with CuPy and a CUDA device (see README "GPU"):
#
#     bash scripts/gpu_check.sh OUT_DIR [STEP...]
#
# Steps (default: tests ties kernels): tests = pytest tests/gpu; ties = the strip tie points' and the SIFT
# pipeline's GPU tests (they need rasterio and pydantic: wheels in .whl/ are installed to /tmp/site first when
# present: scripts/gpu_wheels.sh); kernels = bench/kernels.py --large; strips = bench/strips.py on STRIPS_FRAMES
# (40) full-size frames with STRIPS_OPTIONS (JSON, e.g. '{"threads": 4}': strip pairs at once on the GPU) and its
# parts on STRIPS_PROCESSES worker processes (1: threads; a list such as "6 12": a run each, the frames rendered once).
# mosaic = bench/mosaic_vs_opencv.py (ours against cv2.Stitcher on the machine's cores) on each folder of photos in
# .bench-data/ (`scripts/gpu_wheels.sh mosaic` puts budapest1-6 and the Brighton strip at 2048 px there: ../shared
# does not travel) and a synthetic GPS flight of MOSAIC_SYNTHETIC (30) frames; MOSAIC_REPEAT (3) runs of each side.
# Each step has its own time limit and writes its log to OUT_DIR, so one that fails or hangs leaves the others'.
set -uo pipefail
out=${1:?usage: gpu_check.sh OUT_DIR [STEP...]}
shift
steps=${*:-tests ties kernels}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
py=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH=/tmp/site
fi
{
    date -u
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
    "$py" -c "import sys, numpy, scipy, cv2, cupy; print(sys.version.split()[0], 'numpy', numpy.__version__,
'scipy', scipy.__version__, 'cv2', cv2.__version__, 'cupy', cupy.__version__, 'cuda runtime',
cupy.cuda.runtime.runtimeGetVersion(), 'devices', cupy.cuda.runtime.getDeviceCount(), 'cores', __import__('os').cpu_count())"
} 2>&1 | tee "$out/env.txt"
pytest=("$py" -m pytest -q -ra --tb=short -p no:cacheprovider --durations=8)
for step in $steps; do
    started=$(date +%s)
    case $step in
    tests) timeout 200 "${pytest[@]}" tests/gpu 2>&1 | tee "$out/tests.txt" ;;
    ties)
        timeout 150 "${pytest[@]}" tests/unit/test_strip_ties.py \
            "tests/unit/test_pipeline_truth.py::test_gpu_sift_pipeline_matches_the_truth" 2>&1 | tee "$out/ties.txt"
        ;;
    kernels) timeout 240 "$py" bench/kernels.py --large --json "$out/kernels.json" 2>&1 | tee "$out/kernels.txt" ;;
    strips)
        # one run per count in STRIPS_PROCESSES (e.g. "6 12"), the frames rendered once (kept in /tmp/strip-frames)
        for n in ${STRIPS_PROCESSES:-1}; do
            timeout "${STRIPS_TIMEOUT:-420}" "$py" bench/strips.py --frames "${STRIPS_FRAMES:-40}" \
                --options "${STRIPS_OPTIONS:-{\}}" --processes "$n" --render-processes "$(nproc)" \
                --keep /tmp/strip-frames --json "$out/strips_p$n.json" 2>&1 |
                tee "$out/strips_p$n.txt"
        done
        ;;
    mosaic)
        mapfile -t photos < <(find .bench-data -mindepth 1 -maxdepth 1 -type d 2>/dev/null | sort)
        timeout "${MOSAIC_TIMEOUT:-420}" "$py" bench/mosaic_vs_opencv.py "${photos[@]}" \
            --synthetic "${MOSAIC_SYNTHETIC:-30}" --repeat "${MOSAIC_REPEAT:-3}" --json "$out/mosaic.json" 2>&1 |
            tee "$out/mosaic.txt"
        ;;
    *) echo "unknown step $step" ;;
    esac
    echo "step $step: exit ${PIPESTATUS[0]}, $(($(date +%s) - started)) s" | tee -a "$out/steps.txt"
done
