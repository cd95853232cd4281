# syntax=docker/dockerfile:1
# NePF service image: one image for the API (`nepf serve`) and the worker (`nepf worker`);
# docker-compose.yml builds it once and runs both from it. See docs/SERVICE.md.
#   CPU:  docker build -t nepf .
#   CUDA: docker build -t nepf:cuda --build-arg TORCH_INDEX_URL=https://pypi.org/simple .
# torch: the version pinned in constraints.txt (pyproject.toml only bounds it), from TORCH_INDEX_URL:
# PyTorch's CPU index by default; PyPI's default Linux x86_64 wheel is a CUDA build that brings its
# own CUDA runtime (nvidia-* wheels), so it exists for every pinned version and needs only a host
# NVIDIA driver new enough for it (`python -c "import torch; print(torch.version.cuda)"` in the
# image says which CUDA). A CUDA-specific index (https://download.pytorch.org/whl/cuXYZ) works too
# when it carries the pinned version; an old one (cu121 stops at torch 2.5) makes the build fail.

# ---- web viewer (static files, served by the API at /) ------------------------------------
FROM node:22-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY web/ ./
RUN npm run build

# ---- python ---------------------------------------------------------------------------------
# bookworm: the Debian release .ci/apt-packages.txt was checked on
FROM python:3.11-slim-bookworm AS app
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    NEPF_DATA_DIR=/data \
    NEPF_WEB_DIR=/app/web/dist
# Headless GL for the export previews (VTK offscreen: EGL + OSMesa), the list scripts/install.sh
# installs less the browser-test packages; libgl1/libglib2.0-0/libxrender1: loaded by VTK at import.
COPY .ci/apt-packages.txt /tmp/apt-packages.txt
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      $(grep -v -e '^\s*#' -e '^\s*$' -e '^chromium$' /tmp/apt-packages.txt) \
      libgl1 libglib2.0-0 libxrender1 \
 && rm -rf /var/lib/apt/lists/* /tmp/apt-packages.txt
WORKDIR /app
COPY pyproject.toml constraints.txt ./
# torch first (its own layer): the version pinned in constraints.txt, CPU or CUDA wheel
RUN pip install --index-url "${TORCH_INDEX_URL}" -c constraints.txt torch
COPY nepf_core ./nepf_core
COPY nepf_json ./nepf_json
COPY jobstore ./jobstore
COPY api ./api
COPY worker ./worker
RUN pip install -c constraints.txt ".[service]"
COPY --from=web /web/dist ./web/dist
RUN useradd --create-home --uid 1000 nepf && mkdir -p /data && chown nepf:nepf /data
USER nepf
VOLUME ["/data"]
EXPOSE 8000
# the job store schema is migrated by `nepf serve` (and by `nepf worker`) at start
CMD ["nepf", "serve", "--host", "0.0.0.0", "--port", "8000"]
