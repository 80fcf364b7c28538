# srd-auction API server image (CPU only).
# Build: docker build -t srd-auction .     Run: docker run -p 8000:8000 -v srd-data:/data srd-auction
# The Debian release is pinned by the tag; see the apt note below.
FROM python:3.11-slim-bookworm AS base

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl

# libgomp: torch's OpenMP runtime; libegl/libgl: MuJoCo's optional offscreen renderer.
# Not pinned to versions: Debian replaces a package version when it ships a security fix,
# so a pinned version stops being installable; the bookworm tag above fixes the release.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 libegl1 libgl1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app

# Dependencies first, in their own layer, from the dependency list alone: edits of the source
# or the README do not reinstall torch. The CPU wheel index keeps CUDA packages out; the other
# packages are installed at the versions the tests passed with (constraints.txt).
# EXTRAS names optional dependency groups to add, e.g. --build-arg EXTRAS=ray (compose.yaml).
ARG EXTRAS=""
COPY pyproject.toml constraints.txt ./
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
    && python -c "import os, tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; extras = [d for e in os.environ['EXTRAS'].split(',') if e for d in p['optional-dependencies'][e]]; open('/tmp/requirements.txt', 'w').write('\n'.join(p['dependencies'] + extras))" \
    && pip install -c constraints.txt -r /tmp/requirements.txt

COPY README.md ./
COPY agents ./agents
COPY sim ./sim
COPY screener ./screener
COPY studies ./studies
COPY server ./server
COPY examples ./examples
RUN pip install --no-deps .

# numba compiles lavaland's SRD step on first use (tens of seconds): compile it into the image,
# in a cache the server's user may add to (a CPU unlike the build machine's recompiles once).
ENV NUMBA_CACHE_DIR=/app/numba-cache
RUN srd lavaland --eval-maps 4 --train-maps 4 --out /tmp/warm-up --json > /dev/null \
    && rm -rf /tmp/warm-up \
    && chown -R 10001:10001 /app/numba-cache

RUN useradd --create-home --uid 10001 srd \
    && mkdir -p /data \
    && chown 10001:10001 /data
USER 10001

# The default database, sqlite:///./srd.db, is /data/srd.db from here. SRD_DATABASE_URL is not
# set: a variable would win over the secret file compose.yaml names it with (PostgreSQL).
WORKDIR /data
ENV SRD_DATA_DIR=/data \
    SRD_HOST=0.0.0.0 \
    SRD_PORT=8000
VOLUME ["/data"]
EXPOSE 8000

# Asks the server on the port it was configured with (SRD_PORT), not a fixed one.
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s CMD ["srd", "healthcheck"]

CMD ["srd", "serve"]
