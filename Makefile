# sfm-laserscale — `make demo` and `make test` work from a clean clone on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: all install demo test lint typecheck unit clean

all: install

$(STAMP): pyproject.toml scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[test]"
	$(BIN)/python -c "import open3d, pycolmap, cv2" || { echo "Open3D/pycolmap/OpenCV failed to import: see the message above (Open3D needs Debian's libusb-1.0-0)." >&2; exit 1; }
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/sfm-laserscale demo --out demo_out --overwrite

lint: install
	$(BIN)/ruff check sfm_laserscale tests scripts plugins

typecheck: install
	$(BIN)/mypy sfm_laserscale

unit: install
	$(BIN)/python -m pytest -q -x tests

test: lint typecheck unit

clean:
	rm -rf $(VENV) demo_out build *.egg-info .pytest_cache .mypy_cache .ruff_cache
