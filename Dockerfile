# syntax=docker/dockerfile:1
# NePF service image: API (`nepf serve`) and worker (`nepf worker`) share it; see docs/SERVICE.md.
#   CPU:  docker build -t nepf .
#   CUDA: docker build -t nepf:cuda --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu121 .

# ---- web viewer (static files, served by the API at /) ------------------------------------
FROM node:22-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY web/ ./
RUN npm run build

# ---- python ---------------------------------------------------------------------------------
FROM python:3.11-slim AS app
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    NEPF_DATA_DIR=/data \
    NEPF_WEB_DIR=/app/web/dist
# libGL/libXrender/libglib: VTK (pyvista) and OpenCV-style wheels load them at import
RUN apt-get update \
 && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 libxrender1 libegl1 \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml ./
COPY nepf_core ./nepf_core
COPY api ./api
COPY worker ./worker
COPY bench ./bench
RUN pip install --index-url "${TORCH_INDEX_URL}" torch \
 && pip install . "uvicorn[standard]"
COPY --from=web /web/dist ./web/dist
RUN useradd --create-home --uid 1000 nepf && mkdir -p /data && chown nepf:nepf /data
USER nepf
VOLUME ["/data"]
EXPOSE 8000
CMD ["nepf", "serve", "--host", "0.0.0.0", "--port", "8000"]
