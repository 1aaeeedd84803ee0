# syntax=docker/dockerfile:1.7
#
# Glint API image: `glint serve` (FastAPI + uvicorn) on CPU torch, as a non-root user.
# It holds the whole `glint` package (core, api, worker), so the same image also runs a
# CPU-only worker (`glint worker --device cpu`, see deploy/compose.cpu.yaml).
#
#   docker build -f docker/api.Dockerfile -t glint-api .          # from the repo root
#
# Stages:
#   build    python slim + pip + gcc: a venv in /opt/venv with CPU torch, glint, psycopg,
#            and glint's C kernels prebuilt for each x86-64 level (core/kernels/native_build.py)
#   runtime  python slim + that venv; no compiler, no pip cache, no sources
#
# Base image pinned by tag. Pin the digest too when you cut a release:
#   docker buildx imagetools inspect python:3.11.11-slim-bookworm   # -> sha256:...
#   FROM python:3.11.11-slim-bookworm@sha256:<digest>
# (the build machine that wrote this file could not reach Docker Hub, so no digest is
# recorded here rather than an unverified one).

ARG TORCH_VERSION=2.13.0

FROM python:3.11.11-slim-bookworm AS build
ARG TORCH_VERSION
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
# gcc builds the SIMD compositing kernel (viewer frames) here, so the runtime needs none
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# torch first, from the CPU index, so no resolver ever pulls a CUDA build (as
# scripts/bootstrap.sh does); every other package's torch range accepts it.
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==${TORCH_VERSION}"
WORKDIR /src
# .dockerignore lets only pyproject.toml, README.md and the package folders (core, api,
# worker, viewer_web: whichever exist) into the context
COPY . .
# psycopg: PostgreSQL driver for GLINT_DATABASE_URL=postgresql+psycopg://... (the
# project's "postgres" extra, spelled out so the version range is pinned here too).
RUN pip install . "psycopg[binary]>=3.1,<4" \
    && glint --help >/dev/null \
    && python -m core.kernels.native_build --prebuild /opt/venv/share/glint-native

FROM python:3.11.11-slim-bookworm AS runtime
LABEL org.opencontainers.image.title="glint-api" \
      org.opencontainers.image.description="Glint PGSR-DR reconstruction service: REST API" \
      org.opencontainers.image.licenses="Apache-2.0"
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    GLINT_DATA_DIR=/var/lib/glint \
    GLINT_STORE_DIR=/var/lib/glint/store \
    GLINT_HOST=0.0.0.0 \
    GLINT_PORT=8000 \
    MPLCONFIGDIR=/tmp/matplotlib \
    NUMBA_CACHE_DIR=/tmp/numba \
    GLINT_NATIVE_PREBUILT=/opt/venv/share/glint-native
RUN groupadd --system --gid 10001 glint \
    && useradd --system --uid 10001 --gid glint --home-dir /home/glint --create-home glint \
    && install -d -o glint -g glint /var/lib/glint /var/lib/glint/store
COPY --from=build /opt/venv /opt/venv
# used when this image runs a CPU worker (deploy/compose.cpu.yaml)
COPY docker/worker_healthcheck.py /opt/glint/worker_healthcheck.py
USER 10001:10001
WORKDIR /home/glint
VOLUME ["/var/lib/glint"]
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/v1/health' % os.environ.get('GLINT_PORT', '8000'), timeout=4)"]
ENTRYPOINT ["glint"]
CMD ["serve"]
