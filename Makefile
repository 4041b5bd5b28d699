# The two commands of the README: `make demo` and `make test`. Both build .venv themselves.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test check bench models docs papers lint clean

# uv installs the same packages as pip in seconds instead of a minute; pip is the fallback.
# Not compiled to bytecode at install (12.8 s against 1.4 s): the first process that imports a
# module writes its bytecode (below), and most of what is installed is never imported
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	{ $(BIN)/pip install --quiet uv && \
	  $(BIN)/uv pip install --quiet --python $(BIN)/python -e '.[dev,lab,ethercat]'; } \
	  || $(BIN)/pip install --quiet -e '.[dev,lab,ethercat]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hil demo

# demo, test and check let their processes write bytecode even where PYTHONDONTWRITEBYTECODE
# is set (as on some CI machines): the suite starts some 300 processes (hil runs, their
# writers), each of which would compile hil, numpy, scipy... again (0.1-0.35 s each), and
# pytest would rewrite every test module's asserts again in each of its processes (5 s / 2 s).
demo test check papers: export PYTHONDONTWRITEBYTECODE :=

# numpy's BLAS on one thread in every process, as the hil command gives its own (hil/cli/main.py:
# a second thread spins after each call on the core another process needs): the test workers
# and the benchmark scripts import numpy before hil could say so. 7 % less CPU for the suite
test check bench: export OPENBLAS_NUM_THREADS ?= 1

# the whole suite: the 1-2 kHz wall-clock tests (-m realtime) beside the others. The others run
# at nice 10 with 4 workers on the 2 cores (many tests wait on processes, sockets and runs of
# session time), and mypy at nice 19: the wall-clock tests, at nice 0, take a core the moment
# one of their processes wakes up and 90 % of what they contend for (their real-time threads
# take it all), so they pass as on a quiet machine, in the same minute as the rest; a niced
# test still runs every few tens of milliseconds (at nice 19 one waited over 100 ms). Their
# output is shown at the end. First, one process collects the suite while another compiles
# hil: each process that imports a module first writes its bytecode (pytest its own, asserts
# rewritten), and five pytest processes and the first hil processes would otherwise all
# compile the same modules at once
test: $(STAMP)
	$(BIN)/ruff check .
	nice -n 19 $(BIN)/mypy > $(VENV)/mypy.log 2>&1 & mypy=$$!; \
	$(BIN)/python -m compileall -q hil > /dev/null & compiled=$$!; \
	$(BIN)/pytest -q --collect-only -p no:cacheprovider > /dev/null 2>&1; wait $$compiled; \
	nice -n 10 $(BIN)/pytest -q -n 4 --dist worksteal -m "not realtime" & tests=$$!; \
	$(BIN)/pytest -q -p no:cacheprovider -m realtime > $(VENV)/realtime.log 2>&1; timed=$$?; \
	wait $$tests; tests=$$?; wait $$mypy; typed=$$?; \
	echo "== the wall-clock tests (-m realtime)"; cat $(VENV)/realtime.log; cat $(VENV)/mypy.log; \
	[ $$tests = 0 ] && [ $$timed = 0 ] && [ $$typed = 0 ]

# what a developer runs before every change (under 45 s): no processes, Ray or long runs; mypy
# beside the tests as in `test`, niced (24.6 s from a fresh clone, its cache cold)
check: $(STAMP)
	$(BIN)/ruff check .
	nice -n 10 $(BIN)/mypy > $(VENV)/mypy.log 2>&1 & mypy=$$!; \
	$(BIN)/pytest -q -n 2 -m "not slow and not realtime" tests; tests=$$?; \
	wait $$mypy; typed=$$?; cat $(VENV)/mypy.log; [ $$tests = 0 ] && [ $$typed = 0 ]

# every benchmark, each to its end even when one before it failed (named at the end); each
# script's --quick is the seconds-long run make test does
bench: $(STAMP)
	$(BIN)/pip install --quiet -r benchmarks/requirements.txt
	@grep -v '^#' benchmarks/optional-requirements.txt | awk '{print $$1}' | while read -r pkg; do \
	  [ -n "$$pkg" ] && { $(BIN)/pip install --quiet "$$pkg" || echo "optional baseline $$pkg not installed: skipped"; }; \
	done; true
	@failed=""; for script in benchmarks/*.py; do echo "== $$script"; \
	  $(BIN)/python $$script < /dev/null || failed="$$failed $$script"; done; \
	[ -z "$$failed" ] || { echo "make bench: failed:$$failed"; exit 1; }

models: $(STAMP)
	PATH="$(CURDIR)/$(BIN):$$PATH" sh hil/configs/models/regenerate.sh

# the site: the references generated from the code (the configuration from its readers, the
# commands from their parsers, the session format from short lockstep runs; tests compare
# them), then MkDocs, strict (a broken link fails) and offline, into site/
docs: $(STAMP)
	$(BIN)/python -m hil.cli.config_reference > docs/CONFIGURATION.md
	$(BIN)/python -m hil.cli.command_reference > docs/reference/commands.md
	$(BIN)/python -m hil.cli.session_reference > docs/reference/sessions.md
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# every paper of hil/cli/paper.py's table reproduced, its report committed under docs/papers (the
# sessions beside it are not: docs/papers/.gitignore); minutes each, in lockstep on the emulators
papers: $(STAMP)
	@for paper in $$($(BIN)/python -c 'from hil.cli.paper import PAPERS; print(*PAPERS)'); do \
	  $(BIN)/hil paper $$paper --out docs/papers || exit 1; done

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build dist site *.egg-info .pytest_cache .ruff_cache
