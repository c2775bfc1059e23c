# Two commands on a fresh machine: `make serve` and `make test`. Each does its own set-up.
VENV := .venv
STAMP := $(VENV)/.installed
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: serve test lint bench stress setup clean

$(STAMP): pyproject.toml scripts/setup_env.sh
	bash scripts/setup_env.sh

setup: $(STAMP)

serve: $(STAMP)
	$(VENV)/bin/python -m slam_engine.kernels  # numba's cache warm: no job compiles at first use
	$(VENV)/bin/lidarmap serve --host $(HOST) --port $(PORT)

test:
	LIDARMAP_SETUP_TEST_DEPS=1 bash scripts/setup_env.sh
	$(VENV)/bin/python -m pytest

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

bench: $(STAMP)
	$(VENV)/bin/python -m slam_engine.kernels  # warm: the first run timed must not compile
	$(VENV)/bin/python -m bench

stress:  ## fuzz (1000 schema-generated requests), then load (50 uploads + jobs, 10 000 streamed chunks)
	LIDARMAP_SETUP_TEST_DEPS=1 bash scripts/setup_env.sh
	$(VENV)/bin/python -m tests.stress.fuzz_service --cases 1000
	$(VENV)/bin/python -m tests.stress.load_service

clean:
	rm -rf $(VENV) .pytest_cache bench/results
