# The same install steps as the Makefile's `venv` target, then `vlmap serve` as a non-root user.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 \
    VLMAP_HOST=0.0.0.0 VLMAP_PORT=8000
RUN useradd --create-home --uid 10001 vlmap
WORKDIR /srv/vlmap

# An index that serves CPU builds of torch 2.13.0 (PyTorch publishes one): the default index's torch is the
# CUDA build, which without its CUDA libraries (left out by --no-deps) cannot even be imported.
ARG TORCH_INDEX_URL
COPY requirements.lock pyproject.toml README.md ./
COPY app ./app
COPY models ./models
# torch first, from that index ("2.13.0+cpu" satisfies the lock's torch==2.13.0, so the lock keeps it); then
# the runtime lock only (no test or lint tools), which is complete, hence --no-deps.
RUN test -n "$TORCH_INDEX_URL" \
 || { echo "build with --build-arg TORCH_INDEX_URL=<an index of CPU builds of torch>" >&2; exit 1; } \
 && python -m venv .venv \
 && .venv/bin/python -m pip install --quiet --upgrade pip \
 && .venv/bin/python -m pip install --quiet --no-deps --index-url "$TORCH_INDEX_URL" torch==2.13.0 \
 && .venv/bin/python -m pip install --quiet --no-deps -r requirements.lock \
 && .venv/bin/python -m pip install --quiet --no-deps -e .

# The embedded session store logs to var/sessions (VLMAP_DATA_DIR); mount a volume there to keep beliefs.
RUN mkdir -p var/sessions && chown -R vlmap var
USER vlmap
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
  CMD .venv/bin/python -c "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2).status != 200)"
CMD [".venv/bin/vlmap", "serve"]
