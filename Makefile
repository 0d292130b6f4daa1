# One command each: `make serve` and `make test` create .venv and install the pinned environment first.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv serve test lint bench openapi clean

venv: $(STAMP)

# The same steps as the Dockerfile. torch==2.13.0 is pinned in requirements.lock: pip takes the CPU
# build that lies on this machine's disk (a bare `torch` would pull a multi-GB CUDA build).
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

serve: $(STAMP)
	HF_HUB_OFFLINE=1 $(VENV)/bin/vlmap serve --host 127.0.0.1 --port 8000

test: $(STAMP)
	HF_HUB_OFFLINE=1 $(PY) -m pytest

lint: $(STAMP)
	$(VENV)/bin/ruff check app tests bench
	$(VENV)/bin/mypy

openapi: $(STAMP)
	$(VENV)/bin/vlmap openapi --out openapi/openapi.json

bench: $(STAMP)
	HF_HUB_OFFLINE=1 $(PY) -m bench.ground_latency

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
