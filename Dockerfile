# One image for every COSMOS 3D Search service; SERVICE picks which one a container runs.
FROM python:3.11-slim-bookworm

# libLLVM 19 lets Mitsuba use its fast llvm_ad_rgb variant (Debian's default LLVM 15 crashes it).
RUN apt-get update \
    && apt-get install -y --no-install-recommends libllvm19 \
    && rm -rf /var/lib/apt/lists/*
ENV DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1

WORKDIR /app
COPY pyproject.toml README.md ./
COPY services ./services
COPY cosmos ./cosmos
RUN pip install --no-cache-dir .
COPY scenes ./scenes
COPY models ./models

# The package finds the built-in scenes next to itself; point it at the copied folder instead.
ENV COSMOS_SCENES_DIR=/app/scenes \
    COSMOS_DETECTOR_MODEL=/app/models/detector.onnx \
    SERVICE=renderer \
    PORT=8001
# A fixed id: the Kubernetes manifests run the containers as it (runAsUser, deploy/k8s).
RUN useradd --create-home --uid 1000 cosmos && mkdir -p /data && chown cosmos /data
USER cosmos
EXPOSE 8000 8001 8002 8003
# Healthy when ready to serve (GET /readyz; /livez only says the process answers). The stages
# need COSMOS_SERVICE_TOKEN, given at run time (docker-compose.yml), never baked in.
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s \
    CMD python -c "import os, urllib.request; urllib.request.urlopen(f'http://127.0.0.1:{os.environ[\"PORT\"]}/readyz', timeout=2)"
# uvicorn with a request head size limit (431) and a deadline for the head (services/common/server.py)
CMD ["sh", "-c", "exec python -m services.common.server services.${SERVICE}.app:app --host 0.0.0.0 --port ${PORT} --max-head-bytes 65536 --head-timeout-s 10"]
