# Two commands on a fresh machine (each does its own setup):
#   make full-comparison      # DEM -> tables -> PBM -> report (PRESET=reduced by default)
#   make test                 # the test suite, including a real LIGGGHTS smoke run
PYTHON ?= python3
PRESET ?= reduced
NP ?= 2
FRESH ?=
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup setup-system setup-python test lint full-comparison validate paper-probe bench clean

setup: setup-system setup-python

# apt only when something is missing, so reruns cost nothing. Slurm and munge let the test
# suite run the cluster path on a one-node cluster of this machine; libpmix-dev holds the
# libpmix.so that Slurm's PMIx plugin loads, for `srun --mpi=pmix` to start LIGGGHTS' ranks.
setup-system:
	@if ! command -v liggghts >/dev/null || ! command -v mpirun >/dev/null \
			|| ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null \
			|| ! dpkg -s libpmix-dev >/dev/null 2>&1; then \
		$(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends \
			liggghts openmpi-bin slurm-wlm munge libpmix-dev; \
	fi

# render (pyvista, VTK) too, so that the tests cover the VTK picture and read the ParaView
# files back with VTK; the tests also check that everything works without it (pyvista hidden
# from the import: the picture drawn by matplotlib, the ParaView files still written)
setup-python:
	$(PYTHON) -m pip install -q -e '.[test,render]'

test: setup
	$(PYTHON) -m pytest

# ruff: the rules, the import order and the layout (pyproject.toml's [tool.ruff]).
lint: setup-python
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .

full-comparison: setup
	$(PYTHON) -m workflows.cli compare --preset $(PRESET) --np $(NP) $(if $(FRESH),--fresh)

# The validation campaign's report from its shipped DEM results: no LIGGGHTS run (a run not
# shipped yet is left out, and named); RUN=1 runs the missing ones, FRESH=1 reruns them all
# (about 1 h of DEM per run on 2 cores: seven campaign runs and the feed-step run).
validate: setup
	$(PYTHON) -m workflows.cli validate $(if $(FRESH),--fresh,$(if $(RUN),,--no-solver))

# The paper's particles on this machine: the paper preset's first 15 s on 2 ranks, stopped
# after 45 min of wall time; rewrites workflows/reference/paper_scale/ (the shipped summary).
paper-probe: setup
	$(PYTHON) -m workflows.cli study paper-scale $(if $(FRESH),--fresh)

bench: setup
	$(PYTHON) -m workflows.cli bench all

clean:
	rm -rf results build *.egg-info .pytest_cache
