# One image that runs every stage of the pipeline: `docker run IMAGE <ede-pipeline arguments>`.
# See README.md, "Batch jobs". The repository (code, params.yaml, dvc.yaml, data/) is mounted at
# /work; the image holds the dependencies and an installed copy of the code, so build it from the
# same commit as the checkout it runs on.
#
#   docker build -t ede .                                     # CPU torch (default)
#   docker build -t ede:cuda --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu126 .
#
# Layers go from the slowest-changing to the fastest: system packages, torch, the other packages
# of requirements.lock, then the code. Editing code rebuilds only the last, small layer.
FROM docker.io/library/debian:bookworm-slim

# Debian's python3 (3.11 on bookworm) in a venv; git for DVC; Mesa's software EGL and OSMesa so
# MuJoCo renders headless with no GPU and no display (MUJOCO_GL=egl, or osmesa); g++ and Python's
# headers for torch.compile's CPU kernels, so that td3.compile's default (auto) compiles a long
# run's update here, faster; it keeps what it compiled in TORCHINDUCTOR_CACHE_DIR,
# a folder to mount to keep it between jobs on one machine (docs/performance.md).
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        ca-certificates git python3 python3-venv g++ python3-dev \
        libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libosmesa6 \
    && apt-get clean && rm -rf /var/lib/apt/lists/* \
    && git config --system --add safe.directory '*'

ENV VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    MUJOCO_GL=egl \
    PYOPENGL_PLATFORM=egl \
    TORCHINDUCTOR_CACHE_DIR=/tmp/torchinductor

# Debian's pip; setuptools and wheel come at their locked versions with the rest of the lock.
RUN python3 -m venv "$VIRTUAL_ENV"

# torch alone first: the largest layer, changed only by the build arguments. It comes from
# TORCH_INDEX_URL, PyTorch's CPU-only index by default (a plain `pip install torch` pulls GBs of
# CUDA libraries; a CUDA index gives a CUDA build, to run with `--gpus all`) — unless a torch wheel
# sits in docker/wheels/ (git-ignored, mounted for this step only), which is then used as it is.
# TORCH_VERSION is requirements.lock's (tests/test_lock.py checks it); the build is the index's.
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_VERSION=2.13.0
RUN --mount=type=bind,source=docker/wheels,target=/wheels \
    if ls /wheels/torch-"$TORCH_VERSION"*.whl >/dev/null 2>&1; \
    then pip install --no-deps --find-links /wheels "torch==$TORCH_VERSION"; \
    else pip install --index-url "$TORCH_INDEX_URL" --extra-index-url https://pypi.org/simple \
        "torch==$TORCH_VERSION"; \
    fi

# Every other package of requirements.lock, the same set `make install` puts in .venv (every extra:
# dvc-s3 for S3 stores, Ray for Ray nodes), each at its locked version and checked against its
# locked hashes. Only a change of the lock reruns this.
COPY requirements.lock scripts/lock.py /tmp/lock/
RUN python3 /tmp/lock/lock.py select /tmp/lock/requirements.lock --without torch > /tmp/lock/rest.lock \
    && pip install --require-hashes --no-deps -r /tmp/lock/rest.lock \
    && rm -rf /tmp/lock

# The code (a regular install) and the batch-job script.
COPY pyproject.toml README.md /tmp/ede/
COPY ede /tmp/ede/ede
COPY envs /tmp/ede/envs
COPY pipeline /tmp/ede/pipeline
COPY scripts/batch-job.sh /tmp/ede/scripts/
RUN pip install --no-deps --no-build-isolation /tmp/ede \
    && pip check \
    && install -m 755 /tmp/ede/scripts/batch-job.sh /usr/local/bin/batch-job \
    && rm -rf /tmp/ede

# The commit the code came from, which every run's run.json records (an installed copy has no git
# of its own): `docker build --build-arg EDE_COMMIT=$(git rev-parse HEAD) ...`.
ARG EDE_COMMIT=
ENV EDE_COMMIT=$EDE_COMMIT

# A non-root user. Run with `--user "$(id -u):$(id -g)"` so files written to the mounted checkout
# belong to you; HOME is writable by any user for the tools' caches.
RUN useradd --create-home --uid 1000 --shell /bin/bash ede && chmod 1777 /home/ede
ENV HOME=/home/ede
USER ede
WORKDIR /work
VOLUME /work

ENTRYPOINT ["ede-pipeline"]
CMD ["--help"]
