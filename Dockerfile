# srd-auction API server image (CPU only).
# Build: docker build -t srd-auction .     Run: docker run -p 8000:8000 -v srd-data:/data srd-auction
FROM python:3.11-slim AS base

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl

# libgomp: torch's OpenMP runtime; libegl/libgl: MuJoCo's optional offscreen renderer.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 libegl1 libgl1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app

# Dependencies first, in their own layer: source edits do not reinstall torch.
# The CPU wheel index keeps several GB of CUDA packages out of the image.
COPY pyproject.toml README.md ./
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
    && python -c "import tomllib; deps = tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']; open('/tmp/requirements.txt', 'w').write('\n'.join(deps))" \
    && pip install -r /tmp/requirements.txt

COPY agents ./agents
COPY sim ./sim
COPY screener ./screener
COPY server ./server
COPY examples ./examples
RUN pip install --no-deps .

RUN useradd --create-home --uid 10001 srd \
    && mkdir -p /data \
    && chown srd:srd /data
USER srd

ENV SRD_DATABASE_URL=sqlite:////data/srd.db \
    SRD_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=20s \
    CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz').status == 200 else 1)"

CMD ["srd", "serve", "--host", "0.0.0.0", "--port", "8000"]
