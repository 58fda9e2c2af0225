# Entry points: `make demo`, `make test`, and `make bench` (the CPU benchmark of the README's
# Performance section). Each creates .venv on first use. `make clean` removes .venv, the
# pytest cache and the demo's outputs/demo (not outputs/eval or other results of yours).
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml constraints.txt
	$(BIN)/python -m pip install -q -e ".[test]" -c constraints.txt
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/sav-jax demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder tests

bench: $(STAMP)
	$(BIN)/sav-jax bench --frames 5 --height 128 --width 256 --iters 8

clean:
	rm -rf $(VENV) outputs/demo .pytest_cache
