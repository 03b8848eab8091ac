# The README's two commands: `make demo` and `make test`. Both set everything up first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.dvpmvs-installed

.PHONY: setup demo test clean

$(STAMP): pyproject.toml setup.py plugins/classic/pyproject.toml $(wildcard dvpmvs/*.pyx dvpmvs/*.pxd evaluation/*.pyx)
	./scripts/system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]" -e ./plugins/classic
	touch $(STAMP)

setup: $(STAMP)

# Until the dense stage lands (issue 4) the demo stops after checking the installation.
demo: setup
	$(BIN)/dvpmvs --help
	$(BIN)/dvpmvs plugins
	@echo
	@echo "dvpmvs is installed in $(VENV). The demo (dense stage on the embedded scene, with"
	@echo "evaluation) arrives with the estimator; until then 'make demo' stops here."

test: setup
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) build *.egg-info dvpmvs/*.so dvpmvs/_*.c evaluation/*.so evaluation/_*.c
