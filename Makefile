# sefm-recon: `make demo` and `make test` set everything up on a fresh Debian/Ubuntu machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
TESTED := $(VENV)/.installed-test
# Quiet pip: no version notice, no root-user notice, and no build-backend warnings (setuptools'
# "Editable installation" box, which new pip shows even with -q); errors still print. The
# libraries' releases are those of constraints.txt (the figures in docs/ were measured with them).
PIP    := PYTHONWARNINGS=ignore $(BIN)/pip install -q --disable-pip-version-check --root-user-action=ignore \
          -c constraints.txt
SAMPLE := data_samples/scene
DEMO   := demo_out

.PHONY: install install-test sysdeps colmap demo test bench sample clean

# The package alone (what demo, bench and sample need); install-test adds pytest and hypothesis.
install: sysdeps $(STAMP)
install-test: install $(TESTED)

# open3d needs the system library libusb-1.0-0.
sysdeps:
	@if ! $(PYTHON) -c "import ctypes.util, sys; sys.exit(ctypes.util.find_library('usb-1.0') is None)"; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing libusb-1.0-0 (needed by open3d) with apt-get"; \
	    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "error: open3d needs the system library libusb-1.0-0: run 'sudo apt-get install libusb-1.0-0' and then make again" >&2; \
	    exit 1; \
	  fi; \
	fi

# The COLMAP binary, for the integration test that runs the README's COLMAP steps (it skips without
# one): the distribution's package (COLMAP 3.8 on Debian 12), installed when root with apt-get.
colmap:
	@if ! command -v colmap >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing colmap (for the COLMAP integration test) with apt-get"; \
	    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq colmap >/dev/null; \
	  else \
	    echo "note: no colmap binary; the COLMAP integration test will skip ('sudo apt-get install colmap')"; \
	  fi; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@echo "installing sefm-recon and its dependencies into $(VENV) (a few minutes the first time)"
	@$(PYTHON) -m venv $(VENV)
	@$(PIP) -e .
	@touch $(STAMP)

$(TESTED): $(STAMP)
	@$(PIP) -e '.[test]'
	@touch $(TESTED)

demo: install
	$(BIN)/sefm-recon pair $(SAMPLE)/images/view_000.jpg $(SAMPLE)/images/view_001.jpg \
	  --camera "$$(cat $(SAMPLE)/camera.txt)" -o $(DEMO) --overwrite
	@echo "open $(DEMO)/points.ply or $(DEMO)/mesh.ply in MeshLab; $(DEMO)/matches.png shows the matches"

test: install-test colmap
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/sefm-recon bench

# Regenerate the bundled sample pair (deterministic).
sample: install
	$(BIN)/python scripts/make_sample.py

clean:
	rm -rf $(DEMO) .pytest_cache build *.egg-info
