# The two commands of the README: `make demo` and `make test`. Both build .venv themselves.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test check bench models lint clean

# uv installs the same packages as pip in seconds instead of a minute; pip is the fallback.
# Compiled to bytecode at install, as pip does: with PYTHONDONTWRITEBYTECODE set, every process
# of the suite would compile numpy, scipy... again (0.25 s more for a bare run's imports)
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	{ $(BIN)/pip install --quiet uv && \
	  $(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[dev]'; } \
	  || $(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hil demo

# the whole suite: everything but the 1-2 kHz wall-clock tests on both cores, then those alone.
# Not more workers, nor mypy beside them: 3 workers with mypy ran the tests in 175-230 s instead
# of 225 s, but some tests of emulator processes on the wall clock failed under that load
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q -n 2 --dist worksteal -m "not realtime"
	$(BIN)/pytest -q -m realtime

# what a developer runs before every change (under a minute): no processes, Ray or long runs
check: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q -n 2 -m "not slow and not realtime" tests

bench: $(STAMP)
	$(BIN)/pip install --quiet -r benchmarks/requirements.txt
	@grep -v '^#' benchmarks/optional-requirements.txt | awk '{print $$1}' | while read -r pkg; do \
	  [ -n "$$pkg" ] && { $(BIN)/pip install --quiet "$$pkg" || echo "optional baseline $$pkg not installed: skipped"; }; \
	done; true
	@for script in benchmarks/*.py; do echo "== $$script"; $(BIN)/python $$script || exit 1; done

models: $(STAMP)
	PATH="$(CURDIR)/$(BIN):$$PATH" sh hil/configs/models/regenerate.sh

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache .ruff_cache
