# One command each: `make serve` and `make test` create .venv and install the pinned environment first.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
RUNTIME := $(VENV)/.runtime
DEV     := $(VENV)/.dev

.PHONY: venv serve test lint bench bench-fleet bench-footprint openapi clean

venv: $(DEV)

# The runtime, as the Dockerfile installs it. torch==2.13.0 is pinned in requirements.lock: pip takes the CPU
# build that lies on this machine's disk (a bare `torch` would pull a multi-GB CUDA build). Both locks are
# complete (every package, pinned), so they install with --no-deps: the runtime leaves out what the service
# never imports although a dependency's metadata asks for it (requirements-dev.lock says which).
$(RUNTIME): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-deps -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(RUNTIME)

# Tests, lint and the offline tools (eval, sim, train plots) on top of the runtime.
$(DEV): $(RUNTIME) requirements-dev.lock
	$(PY) -m pip install --quiet --no-deps -r requirements-dev.lock
	touch $(DEV)

serve: $(RUNTIME)
	HF_HUB_OFFLINE=1 $(VENV)/bin/vlmap serve --host 127.0.0.1 --port 8000

test: $(DEV)
	HF_HUB_OFFLINE=1 $(PY) -m pytest

lint: $(DEV)
	$(VENV)/bin/ruff check app tests bench
	$(VENV)/bin/mypy

openapi: $(DEV)
	$(VENV)/bin/vlmap openapi --out openapi/openapi.json

# Benchmarks print figures (the README's Performance section quotes them); they assert nothing.
bench: $(DEV)
	HF_HUB_OFFLINE=1 $(PY) -m bench.ground_latency
	@# OctoMap beside VL-Map in bench.fusion_kernel: Debian's liboctomap-dev (installed when missing, as root
	@# with apt-get) and bench/octomap_harness.cpp built into var/bench; skipped, saying why, without them.
	@if [ ! -f /usr/include/octomap/OcTree.h ] && command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then \
	  echo "bench: installing liboctomap-dev"; \
	  apt-get install -y -qq liboctomap-dev >/dev/null 2>&1 || \
	  { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq liboctomap-dev >/dev/null 2>&1; } || \
	  echo "bench: could not install liboctomap-dev"; \
	fi
	@mkdir -p var/bench && rm -f var/bench/octomap_harness
	@if ! command -v $(CXX) >/dev/null; then echo "bench: OctoMap skipped: no C++ compiler ($(CXX))"; \
	elif [ ! -f /usr/include/octomap/OcTree.h ]; then echo "bench: OctoMap skipped: liboctomap-dev missing"; \
	else $(CXX) -O2 -std=c++17 -o var/bench/octomap_harness bench/octomap_harness.cpp -loctomap -loctomath \
	  || echo "bench: OctoMap skipped: the harness did not build"; fi
	HF_HUB_OFFLINE=1 $(PY) -m bench.fusion_kernel --octomap-harness var/bench/octomap_harness --profile
	$(if $(BASELINE),HF_HUB_OFFLINE=1 $(PY) -m bench.fusion_ab --baseline $(BASELINE))
	HF_HUB_OFFLINE=1 $(PY) -m bench.sessions_e2e
	HF_HUB_OFFLINE=1 $(PY) -m bench.abuse
	$(MAKE) bench-fleet

# 20 robots + 5 dashboards for 60 s on two replicas sharing Redis, then the faults (needs redis-server).
bench-fleet: $(DEV)
	HF_HUB_OFFLINE=1 $(PY) -m bench.fleet

# What a replica costs against the code of BASELINE (a checkout, e.g. `git worktree add /tmp/before HEAD~5`):
# install sizes (a runtime-only venv is built for it), time to ready, RSS idle and with live sessions.
bench-footprint: $(DEV)
	rm -rf var/bench/runtime-venv
	$(PYTHON) -m venv var/bench/runtime-venv
	var/bench/runtime-venv/bin/python -m pip install --quiet --no-deps -r requirements.lock
	HF_HUB_OFFLINE=1 $(PY) -m bench.footprint --runtime-venv var/bench/runtime-venv $(if $(BASELINE),--baseline $(BASELINE))

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
