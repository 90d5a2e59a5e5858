# ifnet-serve: the registration HTTP service (FastAPI + uvicorn + ONNX Runtime), no torch.
#
#   docker build -t ifnet-serve .
#   docker run --rm -p 127.0.0.1:8000:8000 --cpus 2 ifnet-serve
#
# Build with the classic builder or BuildKit alike. Extra CA certificates placed in docker/ca/*.crt
# (for a TLS-intercepting proxy between the build and PyPI) are trusted by the build stage only;
# they never reach the runtime image.

ARG BASE_IMAGE=debian:bookworm-slim

# ---------------------------------------------------------------- build: venv with the `serve` extra
FROM ${BASE_IMAGE} AS build
# Lets a cleanup find this stage's leftover image: `docker image prune --filter label=ifnet-serve.stage=build`.
LABEL ifnet-serve.stage=build

ENV DEBIAN_FRONTEND=noninteractive \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_DEFAULT_TIMEOUT=120 \
    PIP_CERT=/etc/ssl/certs/ca-certificates.crt

RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
 && rm -rf /var/lib/apt/lists/*

# Optional extra CAs; the directory holds at least a .gitkeep, so the COPY never fails.
COPY docker/ca/ /tmp/extra-ca/
RUN find /tmp/extra-ca -maxdepth 1 -name '*.crt' -exec cp {} /usr/local/share/ca-certificates/ \; \
 && update-ca-certificates >/dev/null \
 && rm -rf /tmp/extra-ca

# Dependencies first (the project's runtime deps plus the `serve` extra, read from pyproject.toml),
# so that changes to the service code do not reinstall them. Not needed at run time, so removed:
# pip, the libraries' test suites, ONNX Runtime's model-conversion tooling and its C-API library
# (libonnxruntime.so: the Python binding is self-contained and never loads it). Bytecode
# is compiled here because the runtime user cannot write it; for SciPy (large, mostly unused)
# only the modules the service imports are compiled, in the runtime stage.
COPY pyproject.toml /src/pyproject.toml
RUN python3 -c "import tomllib; p = tomllib.load(open('/src/pyproject.toml', 'rb'))['project']; \
print('\n'.join(p['dependencies'] + p['optional-dependencies']['serve']))" > /src/requirements.txt \
 && cat /src/requirements.txt \
 && python3 -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-compile -r /src/requirements.txt \
 && if /opt/venv/bin/python -c "import torch" 2>/dev/null; then echo "torch must not be in the image" >&2; exit 1; fi \
 && /opt/venv/bin/pip uninstall -y pip setuptools >/dev/null \
 && SITE=$(/opt/venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])") \
 && rm -rf "$SITE/onnxruntime/transformers" "$SITE/onnxruntime/quantization" "$SITE/onnxruntime/tools" \
           "$SITE"/onnxruntime/capi/libonnxruntime.so.* \
 && find "$SITE" -depth -type d -name tests -exec rm -rf {} + \
 && find "$SITE" -depth -type d -name __pycache__ -exec rm -rf {} + \
 && /opt/venv/bin/python -m compileall -q -j 0 -x '/site-packages/scipy/' /opt/venv/lib >/dev/null

# ---------------------------------------------------------------- runtime
FROM ${BASE_IMAGE} AS runtime

ENV DEBIAN_FRONTEND=noninteractive
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin \
 && groupadd --system --gid 10001 ifnet \
 && useradd --system --uid 10001 --gid ifnet --home-dir /nonexistent --no-create-home --shell /usr/sbin/nologin ifnet

COPY --from=build /opt/venv /opt/venv
# The service package with its committed model repository (service/models/*.onnx and drafts/).
# `model` contributes only its torch-free modules (the network itself needs torch and stays out).
COPY service /opt/app/service
COPY model/__init__.py model/geometry.py model/artifacts.py /opt/app/model/
COPY docker/healthcheck.py /opt/app/healthcheck.py
# Import what the service uses (which also writes its bytecode) and load the shipped models once
# with this image's ONNX Runtime: an image that could not serve fails to build.
RUN test -f /opt/app/service/models/object.onnx \
 && find /opt/app -depth -type d -name __pycache__ -exec rm -rf {} + \
 && /opt/venv/bin/python -m compileall -q /opt/app >/dev/null \
 && cd /opt/app \
 && /opt/venv/bin/python -c "import service.app, model.geometry, scipy.spatial.transform, small_gicp, kiss_matcher, lzf; \
from service.engine import load_models; from service.settings import Settings; load_models(Settings(threads=1))"

# IFNET_WORKERS and IFNET_THREADS are deliberately unset: the service then runs a worker per CPU
# this container may use (its cgroup CPU quota, e.g. `--cpus 2`, or the CPU affinity mask), and a
# lone model call gets as many threads.
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONPATH=/opt/app \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    IFNET_HOST=0.0.0.0 \
    IFNET_PORT=8000 \
    IFNET_LOG_LEVEL=info

WORKDIR /opt/app
USER 10001:10001
EXPOSE 8000

# Healthy once the model is loaded and warmed up (GET /ready answers 200).
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD ["/opt/venv/bin/python", "/opt/app/healthcheck.py"]

STOPSIGNAL SIGTERM
CMD ["python", "-m", "service"]
