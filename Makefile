# One command each: `make serve` and `make test` create .venv and install the pinned environment first.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv serve test lint bench bench-fleet openapi clean

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

# Benchmarks print figures (the README's Performance section quotes them); they assert nothing.
bench: $(STAMP)
	HF_HUB_OFFLINE=1 $(PY) -m bench.ground_latency
	HF_HUB_OFFLINE=1 $(PY) -m bench.fusion_kernel
	HF_HUB_OFFLINE=1 $(PY) -m bench.sessions_e2e
	HF_HUB_OFFLINE=1 $(PY) -m bench.abuse
	$(MAKE) bench-fleet

# 20 robots + 5 dashboards for 60 s on two replicas sharing Redis, then the faults (needs redis-server).
bench-fleet: $(STAMP)
	HF_HUB_OFFLINE=1 $(PY) -m bench.fleet

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
