# syntax=docker/dockerfile:1
# The API (and the CPU worker, which runs the same image with another command).
#   docker build -t fotoskhema .
#   docker run -p 127.0.0.1:8000:8000 -v fotoskhema-data:/data fotoskhema   # SQLite in /data, no Redis
# docker-compose.yml wires it to Redis, PostgreSQL and the workers.

# Stage 1: the viewer's JavaScript (Leaflet, Swagger UI) from the npm registry, at build time only:
# the running service never reaches a CDN, and Node stays out of the final image.
FROM python:3.11-slim AS web-assets
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends nodejs npm \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /build
COPY web/package.json web/package.json
RUN npm install --prefix web --omit=dev --no-audit --no-fund --loglevel=error

# Stage 2: the Python service.
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
RUN useradd --create-home --uid 10001 --user-group fotoskhema
WORKDIR /app

# The package, with the PostgreSQL driver. A regular (not editable) install, so the viewer's folder
# is named explicitly below instead of being found next to the sources.
COPY pyproject.toml README.md ./
COPY api api
COPY core core
COPY workers workers
COPY gpu_kernels gpu_kernels
RUN pip install ".[postgres]" && rm -rf build *.egg-info

COPY web web
COPY --from=web-assets /build/web/node_modules web/node_modules

# /data is created here, owned by the service user, so a named volume mounted on it starts
# writable (Docker copies the directory's ownership into an empty volume).
RUN mkdir /data && chown fotoskhema:fotoskhema /data
ENV FOTOSKHEMA_DATA_DIR=/data \
    FOTOSKHEMA_WEB_DIR=/app/web
VOLUME ["/data"]
USER fotoskhema
EXPOSE 8000
# All interfaces of the container, which only the published port reaches (compose: 127.0.0.1 only); the
# Host header is checked against FOTOSKHEMA_ALLOWED_HOSTS. --workers defaults to min(4, cores).
CMD ["fotoskhema", "serve", "--host", "0.0.0.0", "--port", "8000"]
