# manifoldneus: `make all SCENE=scan24`, `make test`. Every target sets up .venv when needed.
SCENE ?= synthetic
STAGE ?=
ARGS ?=
PY := .venv/bin/python

.PHONY: all stage test bench report clean setup status

setup: .venv/.installed
.venv/.installed: requirements.txt
	python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt
	touch $@

all: setup
	$(PY) pipeline.py run --scene $(SCENE) $(ARGS)

stage: setup
	@test -n "$(STAGE)" || (echo "usage: make stage STAGE=<name> SCENE=<scene>"; exit 2)
	$(PY) pipeline.py run --scene $(SCENE) --until $(STAGE) $(ARGS)

status: setup
	$(PY) pipeline.py status --scene $(SCENE) $(ARGS)

test: setup
	$(PY) -m pytest -q tests

bench: setup
	$(PY) bench/bench.py --scene $(if $(filter command line,$(origin SCENE)),$(SCENE),scan24) $(ARGS)

clean:
	rm -rf artifacts .pytest_cache
