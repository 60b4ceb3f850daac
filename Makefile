# The two commands: `make demo` and `make test`. Each sets up .venv on a fresh
# Debian 12 (Python 3.11) machine and runs. `make test-qgis` installs QGIS 3.40
# (root) and .venv-qgis, and runs the QGIS provider's tests; `make plugin`
# builds the QGIS plugin zip.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
DEMO_OUTPUT ?= demo_output
PYTEST_ARGS ?=
QGIS_VENV ?= .venv-qgis
PLUGIN_ZIP ?= build/geoortho_qgis.zip

.PHONY: demo test test-qgis plugin venv lint bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml tools/make_venv.sh
	@sh tools/make_venv.sh "$(PYTHON)" "$(VENV)"
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# The package's bytecode, written ahead: an editable install has none, and where
# PYTHONDONTWRITEBYTECODE is set every command and every pool worker would compile
# geoortho from source at start-up (gcp-find on 35 photos: 12 % of its wall time).
# And the compiled kernels (numba's cache: the target fits', the gap fills', the gridding's and the
# orthophoto's line-of-sight march, the mesh's rasterizer): 10 s once.
BYTECODE = $(PY) -m compileall -q geoortho && $(PY) -c "$(WARM)"
WARM = import geoortho.gcp.targets as a, geoortho.core.gapfill as b, geoortho.elevation.grid as c, geoortho.orthophoto.rectify as d, geoortho.products3d.raster_mesh as e, geoortho.core.surface as f; [m.warm() for m in (a, b, c, d, e, f)]

demo: $(STAMP)
	@$(BYTECODE)
	$(PY) -m geoortho demo --output $(DEMO_OUTPUT)

# The test files run on one pytest-xdist worker per core (at most 4; a file stays on one worker,
# so its module fixtures are made once; the longest files first: tests/conftest.py); tests/conftest.py
# makes each session fixture once per run.
# The slowest are listed at the end: the suite's time is watched against CI's 25-minute budget.
TEST_WORKERS ?= -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder --durations=30

test: $(STAMP)
	@sh tools/browser_setup.sh
	@$(BYTECODE)
	$(PY) -m pytest $(TEST_WORKERS) $(PYTEST_ARGS)

test-qgis:
	@sh tools/qgis_setup.sh "$(QGIS_VENV)"
	@$(QGIS_VENV)/bin/python -m compileall -q geoortho
	$(QGIS_VENV)/bin/python -m pytest tests_qgis $(PYTEST_ARGS)

plugin: $(STAMP)
	$(PY) tools/build_plugin.py $(PLUGIN_ZIP)

# ruff (line length enforced), the formatter's check, and mypy on the package.
lint: $(STAMP)
	$(VENV)/bin/ruff check geoortho tests tests_qgis benchmarks tools
	$(VENV)/bin/ruff format --check geoortho tests tests_qgis benchmarks tools
	$(VENV)/bin/mypy geoortho

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) $(QGIS_VENV) $(DEMO_OUTPUT) build *.egg-info
