"""Pipeline workers: Celery tasks over job workspaces, stage logic and pure algorithms."""

import os

# GDAL's block cache is 5 % of the machine's memory per process unless told otherwise: 6.4 GB on a 128 GB host,
# where a strip's stages peaked at twice what they did on 24 GB (bench/strips.py, 16 frames of 75000 x 1800:
# compose 15.5 GiB on the GPU machine). Bounded for every process that imports the stages; a GDAL_CACHEMAX in the
# environment (MB) wins. Each tile of a frame is read by one window or two, so a small cache loses nothing.
GDAL_CACHE_MB = 512
os.environ.setdefault("GDAL_CACHEMAX", str(GDAL_CACHE_MB))
