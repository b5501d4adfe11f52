# scopetwin — the two commands of the README set up a fresh machine by themselves:
#   make run    creates .venv, installs the project (and the LLVM library Mitsuba needs), runs `scopetwin run`
#   make test   the same set-up, then the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: run test test-all lint docs bench bench-full llvm bytecode setup clean

run: setup
	$(VENV)/bin/scopetwin run

# pytest-xdist: two worker processes that take tests as they go and steal from each other at the end (module
# fixtures and the Mitsuba variant stay per process). One file per worker (loadfile) left the heaviest files — two
# inverse fits of 2-3 min each in one file — to one worker at the end: the whole suite 1178 s, against 976 s this way
XDIST  := -n 2 --dist worksteal

# the default before each commit (<= 5 min on 2 cores): everything but the tests marked slow
test: setup
	$(PY) -m pytest $(XDIST) -m "not slow"

# everything (12-14.5 min on 2 cores, measured; the goal is 15): what .ci/run runs
test-all: setup
	$(PY) -m pytest $(XDIST)

setup: $(STAMP) llvm bytecode

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

llvm:
	@sh .ci/ensure-llvm.sh

# the project's own bytecode, as installing its wheel writes it: the editable install writes none, and where the
# environment turns writing it off (PYTHONDONTWRITEBYTECODE) every process compiled every project module it imported:
# 0.09 s of the 0.8 s `scopetwin reconstruct` spends importing (measured alternately, 6 rounds: 0.79-0.82 s without,
# 0.71-0.73 s with). Modules already compiled and unchanged are skipped (0.15 s); an edited one is compiled again
# here, and in memory until then
bytecode: $(STAMP)
	@$(PY) -m compileall -q -j 0 scopetwin scenes recon calib sim instrument

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	@sh .ci/typecheck-tree.sh
	$(VENV)/bin/mypy

# the documentation (docs/: Sphinx, MyST Markdown, autodoc) as HTML in build/docs; warnings are errors
docs: setup
	$(VENV)/bin/sphinx-build -W --keep-going -b html docs build/docs

# the speed table, each row beside a reference timed in the same run (README, "Benchmarks")
bench: setup
	$(PY) benchmarks/speed_table.py

# the same with the long rows: study thesis, inverse reconstruction, make lint + make test
bench-full: setup
	$(PY) benchmarks/speed_table.py --full

clean:
	rm -rf $(VENV) scopetwin-run .pytest_cache
