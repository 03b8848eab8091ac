# The README's two commands: `make demo` and `make test`. Both set everything up first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.dvpmvs-installed

.PHONY: setup demo test test-fast clean

# Each step says what it does and how long it should take (measured: docs/measured_times.json,
# held by tests/test_stated_times.py), and, when it ends, how long it took; pip shows what it
# downloads and builds (dvpmvs's own Cython kernels last). setuptools' note on editable installs
# through a meta-path finder (our evaluation/ and conf/ are mapped into the package) is silenced:
# it warns of folders named like the package in the working directory, which here is the package.
$(STAMP): pyproject.toml setup.py constraints.txt $(wildcard dvpmvs/*.pyx dvpmvs/*.pxd dvpmvs/*/*.pyx dvpmvs/*/*.pxd dvpmvs/*/*.h evaluation/*.pyx)
	@start=$$(date +%s); echo "setup 1/3: system libraries (scripts/system-deps.sh: apt, only for what is missing)"; \
	./scripts/system-deps.sh && echo "setup 1/3: done in $$(( $$(date +%s) - start )) s"
	@start=$$(date +%s); echo "setup 2/3: the virtual environment $(VENV) and a current pip (about 4 s)"; \
	$(PYTHON) -m venv $(VENV) && $(BIN)/python -m pip install --quiet --upgrade pip && \
	echo "setup 2/3: done in $$(( $$(date +%s) - start )) s"
	@start=$$(date +%s); echo "setup 3/3: dvpmvs and its libraries (NumPy, SciPy, OpenCV, Open3D, pycolmap, ONNX Runtime, Dask ...), then its Cython kernels compiled (about 70 s on 2 cores with the wheels at hand; their download, about 730 MB, comes on top)"; \
	PYTHONWARNINGS="ignore:Editable installation" $(BIN)/python -m pip install --progress-bar on -c constraints.txt -e ".[onnx,eval,test,dask]" && \
	echo "setup 3/3: done in $$(( $$(date +%s) - start )) s"
	touch $(STAMP)

setup: $(STAMP)

# The embedded scene: dense stage, fused cloud, evaluation against its ground truth.
demo: setup
	$(BIN)/dvpmvs demo out=dvpmvs_demo

# The tests also use COLMAP's own program and Chromium (the HTML reports) where apt can install
# them (skipped with the reason otherwise).
# Then the smoke tests and the demo on the oldest and the newest Python pyproject.toml claims, side
# by side, each in its own .venv-3.X and copy of the checkout, where this machine has that Python
# (skipped with the reason where not).
# The suite runs on TEST_WORKERS processes; a worker that runs out of tests takes some from the
# other's queue (worksteal), since the documents' tests take minutes each and would otherwise wait
# for one another. The slowest tests are listed, and each stage's time and the whole run's (setup
# included) are printed last, to keep the run's time in view. The workers' runs share the cores, each
# with as many kernel threads as there are cores: OpenMP threads that wait for work give their core
# up instead of spinning on it (OMP_WAIT_POLICY=passive; no result depends on it).
TEST_WORKERS ?= 2
test:
	@start=$$(date +%s); stage=$$start; status=0; \
	lap() { now=$$(date +%s); times="$$times$$1 $$((now - stage)) s, "; stage=$$now; }; \
	$(MAKE) --no-print-directory setup || status=$$?; lap setup; \
	if [ $$status -eq 0 ]; then ./scripts/system-deps.sh --test || status=$$?; lap "system packages"; fi; \
	if [ $$status -eq 0 ]; then \
		OMP_WAIT_POLICY=passive $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal --durations=20 || status=$$?; lap "main suite"; fi; \
	if [ $$status -eq 0 ]; then \
		$(BIN)/python scripts/other_pythons.py --workers $(TEST_WORKERS) || status=$$?; lap "other Pythons"; fi; \
	echo "make test: $$([ $$status -eq 0 ] && echo passed || echo FAILED) in $$(( $$(date +%s) - start )) s ($${times%, })"; \
	exit $$status

# The fast suite: every test but those marked slow (the end-to-end runs of the documents).
test-fast: setup
	OMP_WAIT_POLICY=passive $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal -m "not slow"

clean:
	rm -rf $(VENV) .venv-3.* .venv-wheel* build *.egg-info dvpmvs/*.so dvpmvs/_*.c dvpmvs/*/*.so dvpmvs/*/_*.c evaluation/*.so evaluation/_*.c
