# One image for both roles of the render service: `dosppm server` and
# `dosppm worker` (see docker-compose.yml and deploy/README.md).
#
#   docker build -t dosppm .                  # from the official Python image
#   docker build --build-arg BASE=local/bookworm -t dosppm .
#
# BASE is any Debian 12 image with python3 (3.11 or later) and its venv
# module: the official python:3.12-slim-bookworm by default; the CI, which
# reaches no image registry, makes one with debootstrap (.ci/compose-check).
ARG BASE=python:3.12-slim-bookworm
FROM ${BASE}

ENV LANG=C.UTF-8 \
    PATH=/opt/dosppm/bin:$PATH \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_THREADING_LAYER=threadsafe

# numba's parallel kernels are called from several threads at once (the
# server's statistics thread beside its main loop), which needs a thread-safe
# threading layer: OpenMP (libgomp1) here. Without it numba falls back to its
# "workqueue" layer and aborts the render ("Concurrent access has been
# detected"); NUMBA_THREADING_LAYER=threadsafe turns that into an error at
# the first parallel call instead.
RUN dpkg -s libgomp1 >/dev/null 2>&1 || { \
      apt-get update -qq \
      && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends libgomp1 >/dev/null \
      && rm -rf /var/lib/apt/lists/*; }

# Dependencies first, from pyproject.toml alone: this layer is rebuilt only
# when the dependency list changes, not on every source edit.
COPY pyproject.toml /src/pyproject.toml
RUN python3 -m venv /opt/dosppm \
 && python3 -c "import tomllib; print('\n'.join(tomllib.load(open('/src/pyproject.toml', 'rb'))['project']['dependencies']))" \
      > /tmp/requirements.txt \
 && pip install -q -r /tmp/requirements.txt \
 && rm /tmp/requirements.txt

# The project itself (a regular, non-editable install): the library and
# the services. The harness (harness/: dosppm bench, reference, compare,
# evaluate) stays out of the image; those verbs say so in one line here.
COPY README.md /src/README.md
COPY dosppm_core /src/dosppm_core
COPY services /src/services
RUN pip install -q --no-deps /src && rm -rf /src

# Compile every numba kernel into numba's cache (the __pycache__ folders
# beside the installed modules) so that containers start rendering at once
# instead of compiling for about a minute each. numba's cache is specific to
# the CPU it was compiled on: on a host with another CPU the kernels are
# compiled again at first use (see deploy/README.md).
RUN cd / && python -c "from services.local import warm_kernels; warm_kernels()" \
 && python -c "from services.progress import kernels_cached; assert kernels_cached(), 'numba cache is empty'"

# Tracer health probe (docker-compose.yml's healthcheck for the tracer).
COPY deploy/tracer-health.py /usr/local/bin/dosppm-tracer-health

WORKDIR /out
EXPOSE 5555 5600 8080
ENTRYPOINT ["dosppm"]
CMD ["--help"]
