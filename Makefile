# jaxflare: set-up, demo, tests and benchmarks. Every target creates .venv when it is missing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

# Keep caches inside the checkout: matplotlib, colour-science and Jupyter write under $HOME otherwise.
export MPLCONFIGDIR := $(CURDIR)/.cache/matplotlib
export XDG_CACHE_HOME := $(CURDIR)/.cache
export IPYTHONDIR := $(CURDIR)/.cache/ipython
export JUPYTER_CONFIG_DIR := $(CURDIR)/.cache/jupyter
export JUPYTER_DATA_DIR := $(CURDIR)/.cache/jupyter-data
export JUPYTER_RUNTIME_DIR := $(CURDIR)/.cache/jupyter-runtime
export MPLBACKEND := Agg

.PHONY: demo test bench venv clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/jaxflare demo --out out/demo

# pytest exits 5 when it collects no tests: report it instead of failing (make would turn any
# non-zero status into its own exit code 2, so the distinction has to be made here). A crashed
# worker ends the run (--max-worker-restart 0): after a restart, xdist's loadfile scheduler has
# hung until CI's time limit.
test: $(STAMP)
	@$(BIN)/python -m pytest -q -n 2 --dist loadfile --max-worker-restart 0; status=$$?; \
	if [ $$status -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi; exit $$status

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[test,bench]"
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf out .cache .pytest_cache build *.egg-info
