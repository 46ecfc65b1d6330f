# diffaccel developer commands.  `make demo` and `make test` install on first use.
PYTHON ?= python3
VENV ?= .venv
# CPU build of PyTorch by default; override e.g. `make install TORCH=torch` for CUDA.
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
OUT ?= demo_output

.PHONY: install demo test lint format bench docs clean

$(BIN)/diffaccel:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet "$(TORCH)"
	$(BIN)/pip install --quiet -e ".[test]"

install: $(BIN)/diffaccel

# the demo owns $(OUT) (default demo_output/) and replaces it on each run
demo: $(BIN)/diffaccel
	$(BIN)/diffaccel demo --out $(OUT) --force

test: $(BIN)/diffaccel
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/python -m pytest -q --doctest-modules src/diffaccel tests

lint: $(BIN)/diffaccel
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks

format: $(BIN)/diffaccel
	$(BIN)/ruff format src tests benchmarks
	$(BIN)/ruff check --fix src tests benchmarks

# every CPU benchmark; `make bench STORE=--store` also rewrites benchmarks/results/
bench: $(BIN)/diffaccel
	$(BIN)/pip install --quiet -e ".[bench]"
	for b in benchmarks/[!_]*.py; do echo "== $$b"; $(BIN)/python $$b $(STORE) || exit 1; done

# the docs site: runs the tutorials, writes the benchmarks page, builds site/
# with warnings as errors (docs/index.md says why MkDocs)
docs: $(BIN)/diffaccel
	$(BIN)/pip install --quiet -e ".[docs]"
	$(BIN)/python docs/tutorials/run.py
	$(BIN)/python docs/benchmarks_page.py
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

clean:
	rm -rf $(VENV) $(OUT) site docs/generated .pytest_cache .ruff_cache
