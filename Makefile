PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# evo (GPL-3.0) is a test-only oracle for `vio eval`; it lives in its own venv and is only run as a program.
EVO_VENV := .venv-evo
EVO_STAMP := $(EVO_VENV)/.installed

.PHONY: venv demo test lint bench clean

venv: $(STAMP) $(EVO_STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

$(EVO_STAMP):
	test -x $(EVO_VENV)/bin/python || $(PY) -m venv $(EVO_VENV)
	printf '*\n' > $(EVO_VENV)/.gitignore
	$(EVO_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(EVO_VENV)/bin/python -m pip install --quiet evo
	touch $(EVO_STAMP)

demo: venv
	$(BIN)/vio demo --out out/demo

test: venv
	$(BIN)/python -m pytest -q

lint: venv
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

bench: venv
	$(BIN)/vio bench --suite quick --out out/bench

clean:
	rm -rf out build *.egg-info
