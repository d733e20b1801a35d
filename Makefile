# redarm_ros developer entry points. `make test` and `make demo` are the two README commands: both set
# the environment up themselves (scripts/setup_env.sh: .venv, pinned wheels, `pip install -e .`, the
# interfaces package built into the venv), idempotently; a second run skips every finished step.
# Everything that may start ROS runs through scripts/ros_sandbox.sh (SHM-only DDS, random
# ROS_DOMAIN_ID, private network namespace when possible). See docs/setup.md.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test

VENV := .venv
PY := $(VENV)/bin/python
SANDBOX := scripts/ros_sandbox.sh
DEMO_ARGS ?=
PYTEST_ARGS ?=
# pytest-xdist workers for `make test` (0: none). The stack tests run in order on one or two of them (test/conftest.py).
TEST_WORKERS ?= 3
# Extra arguments for every benchmark; `make bench BENCH_FULL=1` runs them in full (see scripts/run_benchmarks.sh).
BENCH_ARGS ?=

.PHONY: setup test lint demo bench clean distclean

setup:
	@bash scripts/setup_env.sh

lint: setup
	$(VENV)/bin/ruff check .

# Lint and tests both run; the target fails if either failed. pytest's exit 5 ("no tests collected")
# is reported and not treated as a failure. Bytecode caches are written even where the caller's
# environment sets PYTHONDONTWRITEBYTECODE: the suite starts hundreds of Python processes (nodes,
# simulators, CLIs) and each would compile the package's modules again (about 1 s of CPU a process), and
# every xdist worker would rewrite every test module's asserts again. With workers, one collection
# (beside ruff) first writes those caches once, where the workers starting together would each write
# them (in a fresh clone about 6 s of CPU more than that collection takes).
test: setup
	@if [ -f scripts/setup_uml.sh ]; then bash scripts/setup_uml.sh; fi  # UML guest for SocketCAN tests
	@if [ -f scripts/setup_chromium.sh ]; then bash scripts/setup_chromium.sh; fi  # headless Chromium for the browser test
	@rc=0; warm=; \
	if [ "$(TEST_WORKERS)" -gt 1 ]; then \
	    PYTHONDONTWRITEBYTECODE= $(SANDBOX) $(PY) -m pytest --collect-only -q -p no:cacheprovider $(PYTEST_ARGS) \
	        >/dev/null 2>&1 & warm=$$!; \
	fi; \
	echo "+ ruff check ."; $(VENV)/bin/ruff check . || rc=$$?; \
	if [ -n "$$warm" ]; then wait $$warm || true; fi; \
	echo "+ pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)"; \
	prc=0; PYTHONDONTWRITEBYTECODE= $(SANDBOX) $(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS) || prc=$$?; \
	if [ $$prc -eq 5 ]; then echo "make test: pytest collected no tests"; prc=0; fi; \
	if [ $$rc -ne 0 ]; then echo "make test: ruff found problems (exit $$rc)"; fi; \
	if [ $$prc -ne 0 ]; then echo "make test: pytest failed (exit $$prc)"; fi; \
	[ $$rc -eq 0 ] && [ $$prc -eq 0 ]

demo: setup
	$(SANDBOX) $(PY) -m redarm_ros.demo $(DEMO_ARGS)

# Smoke runs (--quick --no-write where supported) unless BENCH_FULL=1.
bench: setup
	$(SANDBOX) scripts/run_benchmarks.sh $(BENCH_ARGS)

# Build products, caches and stamps; the venv stays (`make distclean` removes it too).
clean:
	rm -rf .build build install log demo_output .pytest_cache .ruff_cache .hypothesis *.egg-info \
	    $(VENV)/.redarm-stamps
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
