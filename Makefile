# The two commands of the README: `make demo` and `make test`. Both build .venv themselves.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench models lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hil demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q

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
