# polycc developer entry points. Every target sets up .venv itself on a fresh machine.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
OUT ?= out/demo

# Locally `make test` skips tests marked slow; CI (CI=true) runs everything.
ifeq ($(CI),true)
PYTEST_MARK := --durations=40
else
PYTEST_MARK := -m "not slow"
endif
PYTEST_ARGS ?= -n 2

.PHONY: venv demo test test-all lint bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,bench,dask]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/polycc demo-scene $(OUT)/arena.ply
	$(BIN)/polycc build $(OUT)/arena.ply --flash-kb 64 -o $(OUT)
	$(BIN)/polycc sim $(OUT) --scene $(OUT)/arena.ply --dynamics crazyflie

# When pytest fails, tools/failure_summary.py prints what failed last (CI keeps only the log's tail).
test: $(STAMP)
	$(BIN)/ruff check polycc tests bench tools
	@mkdir -p build
	$(BIN)/python -m pytest $(PYTEST_MARK) $(PYTEST_ARGS) --junitxml=build/test-report.xml \
	  || { rc=$$?; $(BIN)/python tools/failure_summary.py build/test-report.xml $$rc; exit $$rc; }

test-all: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check polycc tests bench tools

bench: $(STAMP)
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) out build *.egg-info
