"""Pipeline workers: Celery tasks over job workspaces, stage logic and pure algorithms."""

import ctypes
import os

# GDAL's block cache is 5 % of the machine's memory per process unless told otherwise: 6.4 GB on a 128 GB host,
# where a strip's stages peaked at twice what they did on 24 GB (bench/strips.py, 16 frames of 75000 x 1800:
# compose 15.5 GiB on the GPU machine). Bounded for every process that imports the stages; a GDAL_CACHEMAX in the
# environment (MB) wins. Each tile of a frame is read by one window or two, so a small cache loses nothing.
GDAL_CACHE_MB = 512
os.environ.setdefault("GDAL_CACHEMAX", str(GDAL_CACHE_MB))

# glibc gives arrays over 128 KiB (its starting threshold) pages of their own and returns them when freed, so a
# stage that makes and drops a window's float copies again and again faults every page in anew: composing one band
# of a 75000 px strip took 600k page faults and 1.5 s of system time in 3.0 s (threads fault under one lock per
# process). Kept in the process up to 32 MiB an array and 256 MiB free at the heap's top: 5k faults, 0.45 s, 2.2 s.
MALLOC_MMAP_THRESHOLD = 32 << 20
MALLOC_TRIM_THRESHOLD = 256 << 20


def _keep_freed_memory() -> None:
    """Set glibc's thresholds (``mallopt``) unless the environment sets them; nothing where libc is not glibc."""
    if any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")):
        return
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl, macOS, Windows
        return
    mallopt(-3, MALLOC_MMAP_THRESHOLD)  # M_MMAP_THRESHOLD
    mallopt(-1, MALLOC_TRIM_THRESHOLD)  # M_TRIM_THRESHOLD


_keep_freed_memory()
