# Quick start: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DOCS_STAMP := $(VENV)/.installed-docs

.PHONY: demo test test-slow notebooks install docs lint format report clean min-versions

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[all,test,lint]'
	touch $(STAMP)

$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	touch $(DOCS_STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/misrgraph demo --out demo-output

# the suite on TEST_WORKERS processes (pytest-xdist; whole files per process, so that a file's
# fixtures are built once; the scenarios many files share are built once per run, tests/conftest.py)
# without the tutorials' notebooks (make notebooks) and the tests marked slow (make test-slow: kill
# trials, whole months and campaigns, the demo); TEST_WORKERS=0 runs it in this process. Each process runs one BLAS
# thread (TEST_BLAS_THREADS): two processes of multi-threaded OpenBLAS on two cores contend and
# slow the heavy tests. The slowest tests are listed at the end.
TEST_WORKERS ?= 2
TEST_BLAS_THREADS ?= 1
test: $(STAMP)
	OPENBLAS_NUM_THREADS=$(TEST_BLAS_THREADS) OMP_NUM_THREADS=$(TEST_BLAS_THREADS) MKL_NUM_THREADS=$(TEST_BLAS_THREADS) \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15 -m "not notebooks and not slow"

# the tests marked slow: end-to-end runs and statistical checks at the sizes users run
test-slow: $(STAMP)
	OPENBLAS_NUM_THREADS=$(TEST_BLAS_THREADS) OMP_NUM_THREADS=$(TEST_BLAS_THREADS) MKL_NUM_THREADS=$(TEST_BLAS_THREADS) \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15 -m "slow and not notebooks"

# the tutorials (docs/tutorials are the notebooks/ they run) executed top to bottom at reduced size
notebooks: $(STAMP)
	OPENBLAS_NUM_THREADS=$(TEST_BLAS_THREADS) OMP_NUM_THREADS=$(TEST_BLAS_THREADS) MKL_NUM_THREADS=$(TEST_BLAS_THREADS) \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m notebooks tests/test_notebooks.py

# the documentation site in build/site, every warning an error
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# the results pages and the README's figures, from the stored bench results in docs/results/data
report: $(STAMP)
	$(BIN)/misrgraph bench report

# every dependency at the floor pyproject.toml declares, in .venv-min, then the suite's fast part
min-versions:
	./.ci/min-versions

clean:
	rm -rf $(VENV) .venv-min demo-output .pytest_cache build .cache
