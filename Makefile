# The two commands: `make run` and `make test`. Everything else they need is set up here.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# One environment in two layers, each with its stamp: what running needs (`make run`), then the
# test and documentation tools on top (`make test`, `make docs`, …), so that `make test` after
# `make run` adds only the tools. uv installs them (the venv's own pip brings it): it resolves
# as pip does but downloads and unpacks in parallel, where pip's one-at-a-time install was most
# of a fresh clone's set-up. --compile-bytecode writes the .pyc files at install, as pip does:
# where PYTHONDONTWRITEBYTECODE is set, every process would otherwise compile all it imports.
RUN_STAMP  := $(VENV)/.installed-run
TEST_STAMP := $(VENV)/.installed-test
# SysIdentPy, the independent FROLS bench/bench_frols.py compares with, caps numpy below the
# version narxwatch runs on: it gets an environment of its own instead of downgrading .venv.
BENCH_VENV  := .venv-bench
BENCH_STAMP := $(BENCH_VENV)/.installed
# pytest-xdist processes for `make test`. Much of the suite waits on servers (uvicorn, PostgreSQL,
# narxwatch workers, Chromium), so two processes take about two thirds of one's time even on two
# busy cores. Whole files go to one process (--dist loadfile): their module fixtures are built once;
# the longest first, in tests/conftest.py's order, which xdist would otherwise replace by the
# number of tests in each file (--no-loadscope-reorder).
TEST_WORKERS ?= 2

.PHONY: run test slow lint bench reproduce docs clean

$(RUN_STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet uv
	$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e .
	touch $@

$(TEST_STAMP): $(RUN_STAMP)
	$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[test]'
	touch $@

run: $(RUN_STAMP)
	$(BIN)/narxwatch db upgrade
	$(BIN)/narxwatch demo-seed
	@echo
	@echo "narxwatch is starting on http://127.0.0.1:8000  (API docs: http://127.0.0.1:8000/docs)"
	@echo "demo admin key (shown once): $$($(BIN)/narxwatch keys create --org demo --role admin)"
	@echo "in another terminal, 'source .venv/bin/activate' puts narxwatch and narxwatch-sim on your PATH"
	@echo
	$(BIN)/narxwatch serve --host 127.0.0.1 --port 8000

$(BENCH_STAMP): pyproject.toml
	$(PYTHON) -m venv $(BENCH_VENV)
	$(BENCH_VENV)/bin/pip install --quiet uv
	$(BENCH_VENV)/bin/uv pip install --quiet --compile-bytecode --python $(BENCH_VENV)/bin/python -e '.[bench]'
	touch $(BENCH_STAMP)

reproduce: $(RUN_STAMP)
	$(BIN)/narxwatch reproduce --out var/reproduce

# numba's kernels are compiled into their cache (harness/kernels.py) beside the site's build and
# the checks, on the core they leave idle: in a fresh clone each pytest process would otherwise
# compile them all at its start, both at once. The project's own modules are compiled there first,
# and the suite's processes may write bytecode (PYTHONDONTWRITEBYTECODE emptied, where the
# environment sets it): the editable install's sources have no .pyc from the install, and each of
# the hundred-odd processes the tests start (servers, workers, commands) would compile those it
# imports again. The .pyc files go to __pycache__/ beside each module, which git ignores, as
# pytest's rewritten test modules do.
test: export PYTHONDONTWRITEBYTECODE =
test: $(TEST_STAMP)
	{ $(BIN)/python -m compileall -q models recordfiles simulator service migrations harness \
		&& $(BIN)/python -m harness.kernels; } & compiling=$$!; \
	$(MAKE) --no-print-directory docs && $(BIN)/ruff check . && $(BIN)/lint-imports \
		&& bash scripts/ensure-postgres.sh && bash scripts/ensure-chromium.sh; \
	checked=$$?; wait $$compiling && exit $$checked
	$(BIN)/pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m "not slow"

# The documentation site, into var/site/ (git-ignored). --strict: a broken link, a missing anchor
# or a reference to code that is gone fails the build, and so `make test`.
docs: $(TEST_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# The Monte Carlo studies marked slow (reduced versions of bench/'s), kept out of `make test`'s
# fifteen minutes.
slow: $(TEST_STAMP)
	$(BIN)/pytest -n $(TEST_WORKERS) -m slow

lint: $(TEST_STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

bench: $(TEST_STAMP) $(BENCH_STAMP)
	$(BIN)/pytest bench --benchmark-only --benchmark-columns=min,median,max,rounds
	$(BENCH_VENV)/bin/python bench/bench_frols.py
	$(BIN)/python bench/dashboard.py


clean:
	rm -rf $(VENV) $(BENCH_VENV) var .pytest_cache .ruff_cache
