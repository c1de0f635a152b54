# manifoldneus: `make all SCENE=scan24`, `make test`. Every target sets up .venv when needed.
# Several scenes: `make all SCENES="scan24 scan24_idr synthetic" ARGS="--executor dask"` (README: "Running on a cluster").
SCENE ?= synthetic
SCENES ?= $(SCENE)
STAGE ?=
TABLE ?=
VALUES ?=
ARGS ?=
PY := .venv/bin/python

.PHONY: all stage test bench bench-refine profile results report sweep clean setup status view

setup: .venv/.installed
# an editable install: the checkout is the code that runs; pyproject.toml lists what it needs
.venv/.installed: pyproject.toml constraints.txt
	@echo "[setup 1/3] a virtual environment in .venv"
	python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	@echo "[setup 2/3] the project and its dependencies (torch, pycolmap, OpenCV, ...: a few minutes, about 2 GB)"
	$(PY) -m pip install -q -c constraints.txt -e ".[dask,dev]"
	@echo "[setup 3/3] the CPU grid kernel (g++, under a minute, once)"
	$(PY) -c "from manifoldneus.neural.grid_encoding import fused_kernel; fused_kernel()"  # builds the CPU grid kernel once
	touch $@

all: setup
	$(PY) pipeline.py run $(foreach s,$(SCENES),--scene $(s)) $(ARGS)

stage: setup
	@test -n "$(STAGE)" || (echo "usage: make stage STAGE=<name> SCENE=<scene>"; exit 2)
	$(PY) pipeline.py run --scene $(SCENE) --until $(STAGE) $(ARGS)

status: setup
	$(PY) pipeline.py status --scene $(SCENE) $(ARGS)

# the run's viewer page (mesh and cameras in a browser; one self-contained HTML file): prints its path
view: setup
	$(PY) pipeline.py view --scene $(SCENE) $(ARGS)

# whole files to two workers, longest first (tests/conftest.py); xdist would otherwise hand out the files with the
# most tests first, and a long file of few tests last
test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder tests

# the bench (the four development scenes unless SCENE or SCENES is given), then README's Results regenerated from
# the latest bench JSON of each scene
BENCH_SCENES = $(if $(filter command line,$(origin SCENES)),$(SCENES),$(if $(filter command line,$(origin SCENE)),$(SCENE),synthetic scan24 scan24_idr scan65_idr))
SEEDS ?= 0,1,2
bench: setup
	$(PY) -m bench.bench $(foreach s,$(BENCH_SCENES),--scene $(s)) --seeds $(SEEDS) $(ARGS)
	$(PY) -m bench.results_md

# do the joint rounds refine their initialisation? synthetic, scan24, scan24_idr, scan65_idr x 3 seeds (README: "Refinement")
bench-refine: setup
	$(PY) -m bench.bench_refine --gt-pose $(if $(filter command line,$(origin SCENE)),--scenes $(SCENE)) $(ARGS)
	$(PY) -m bench.results_md

# where the neural trainer's step spends its time; rays per CPU-second (docs/PERFORMANCE.md)
profile: setup
	$(PY) -m bench.profile_step --scene $(if $(filter command line,$(origin SCENE)),$(SCENE),scan24) $(ARGS)

results: setup
	$(PY) -m bench.results_md

report: setup
	$(PY) pipeline.py report --scene $(SCENE) $(ARGS)

# the supplement's experiments (Tables A3-A6, Fig. A7, Sec. 4.4 sparse views) on the pipeline's cache
sweep: setup
	@test -n "$(TABLE)" || (echo "usage: make sweep TABLE=A3|A4|A5|A6|A7|sparse SCENE=<scene> [VALUES='0.65 0.5']"; exit 2)
	$(PY) -m bench.sweep $(TABLE) --scene $(if $(filter command line,$(origin SCENE)),$(SCENE),scan24) \
		$(if $(VALUES),--values $(VALUES)) $(ARGS)

clean:
	rm -rf artifacts .pytest_cache
