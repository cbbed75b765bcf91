# The two commands: `make run` and `make test`. Everything else they need is set up here.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test lint bench reproduce clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/narxwatch db upgrade
	$(BIN)/narxwatch demo-seed
	@echo
	@echo "narxwatch is starting on http://127.0.0.1:8000  (API docs: http://127.0.0.1:8000/docs)"
	@echo "demo admin key (shown once): $$($(BIN)/narxwatch keys create --org demo --role admin)"
	@echo
	$(BIN)/narxwatch serve --host 127.0.0.1 --port 8000

reproduce: $(STAMP)
	$(BIN)/narxwatch reproduce --out var/reproduce

test: $(STAMP)
	$(BIN)/ruff check .
	bash scripts/ensure-postgres.sh
	$(BIN)/pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/pytest bench --benchmark-only --benchmark-columns=min,median,max,rounds


clean:
	rm -rf $(VENV) var .pytest_cache .ruff_cache
