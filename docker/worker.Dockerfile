# syntax=docker/dockerfile:1.7
#
# Glint GPU worker image: `glint worker` (Celery solo pool: one job at a time, one GPU
# per container)
# with a CUDA build of torch and gsplat's CUDA extension compiled in, so the first job
# does not spend minutes in nvcc.
#
#   docker build -f docker/worker.Dockerfile -t glint-worker .    # from the repo root
#   docker build -f docker/worker.Dockerfile --build-arg TORCH_CUDA_ARCH_LIST="8.9" .
#
# Stages:
#   build    CUDA *devel* image (nvcc, headers) + python3.12-dev + g++: a venv in
#            /opt/venv with torch (CUDA wheel), glint, psycopg, and gsplat built from its
#            sdist for every arch in TORCH_CUDA_ARCH_LIST (-> gsplat/csrc.so)
#   runtime  CUDA *runtime* image + python3.12 + that venv; no nvcc, no compiler
#
# What must agree: CUDA_VERSION (base images) ~ TORCH_CUDA (the PyTorch wheel index,
# cu128 = CUDA 12.8) ~ the host driver (>= the CUDA version's minimum driver). gsplat's
# extension is compiled against the torch in the same venv: change TORCH_VERSION and it
# is rebuilt. Base images are pinned by tag; pin digests too when cutting a release:
#   docker buildx imagetools inspect nvidia/cuda:12.8.1-runtime-ubuntu24.04
#   FROM nvidia/cuda:12.8.1-runtime-ubuntu24.04@sha256:<digest>
# (the machine that wrote this file could not reach Docker Hub, so no digest is recorded
# here rather than an unverified one).

ARG TORCH_VERSION=2.13.0
ARG TORCH_CUDA=cu128
ARG GSPLAT_VERSION=1.5.3
# Turing (T4), Ampere (A100, A10/3090), Ada (L4/L40/4090), Hopper (H100/H200)
ARG TORCH_CUDA_ARCH_LIST="7.5;8.0;8.6;8.9;9.0"

FROM nvidia/cuda:12.8.1-devel-ubuntu24.04 AS build
ARG TORCH_VERSION
ARG TORCH_CUDA
ARG GSPLAT_VERSION
ARG TORCH_CUDA_ARCH_LIST
ARG MAX_JOBS=4
ENV DEBIAN_FRONTEND=noninteractive \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        python3.12 python3.12-venv python3.12-dev g++ \
    && rm -rf /var/lib/apt/lists/*
RUN python3.12 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# torch first, from the PyTorch CUDA index (the CUDA build); the resolver keeps it
RUN pip install --index-url "https://download.pytorch.org/whl/${TORCH_CUDA}" \
        "torch==${TORCH_VERSION}"
# gsplat from source against this torch, for every listed architecture. No GPU is
# needed to compile; TORCH_CUDA_ARCH_LIST replaces the detection of the local GPU.
# The import check fails the build if the extension was not produced (pip would
# otherwise happily install the pure-python part, which JIT-compiles at run time).
RUN pip install "setuptools>=68" "wheel>=0.42" "ninja>=1.11" "numpy>=1.26" \
        "jaxtyping>=0.2.25" "rich>=12" "packaging>=23" \
    && TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST}" MAX_JOBS="${MAX_JOBS}" \
        pip install --no-build-isolation --no-binary=gsplat "gsplat==${GSPLAT_VERSION}" \
    && python -c "from gsplat import csrc; print('gsplat extension:', csrc.__file__)"
WORKDIR /src
# .dockerignore lets only pyproject.toml, README.md and the package folders in
COPY . .
RUN pip install . "psycopg[binary]>=3.1,<4" \
    && glint --help >/dev/null

FROM nvidia/cuda:12.8.1-runtime-ubuntu24.04 AS runtime
LABEL org.opencontainers.image.title="glint-worker" \
      org.opencontainers.image.description="Glint PGSR-DR reconstruction service: CUDA worker" \
      org.opencontainers.image.licenses="Apache-2.0"
ENV DEBIAN_FRONTEND=noninteractive
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3.12 libgomp1 \
    && rm -rf /var/lib/apt/lists/* \
    && groupadd --system --gid 10001 glint \
    && useradd --system --uid 10001 --gid glint --home-dir /home/glint --create-home glint \
    && install -d -o glint -g glint /var/lib/glint /var/lib/glint/store
COPY --from=build /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    GLINT_DATA_DIR=/var/lib/glint \
    GLINT_STORE_DIR=/var/lib/glint/store \
    GLINT_QUEUE_BACKEND=celery \
    MPLCONFIGDIR=/tmp/matplotlib \
    NUMBA_CACHE_DIR=/tmp/numba \
    NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility
USER 10001:10001
WORKDIR /home/glint
VOLUME ["/var/lib/glint"]
# Liveness = this container's row in the workers table is fresh (the worker heartbeats
# from a thread, also during a long job); see docker/worker_healthcheck.py.
COPY docker/worker_healthcheck.py /opt/glint/worker_healthcheck.py
HEALTHCHECK --interval=30s --timeout=20s --start-period=60s --retries=3 \
    CMD ["python", "/opt/glint/worker_healthcheck.py"]
ENTRYPOINT ["glint"]
# one Celery solo-pool process = one job at a time; the container sees one GPU: cuda:0
CMD ["worker", "--device", "cuda:0"]
