# sefm-recon: `make demo` and `make test` set everything up on a fresh Debian/Ubuntu machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SAMPLE := data_samples/scene
DEMO   := demo_out

.PHONY: install sysdeps demo test bench sample clean

install: sysdeps $(STAMP)

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

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	@touch $(STAMP)

demo: install
	$(BIN)/sefm-recon pair $(SAMPLE)/images/view_000.jpg $(SAMPLE)/images/view_001.jpg \
	  --camera "$$(cat $(SAMPLE)/camera.txt)" -o $(DEMO) --overwrite
	@echo "open $(DEMO)/points.ply or $(DEMO)/mesh.ply in MeshLab; $(DEMO)/matches.png shows the matches"

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/sefm-recon bench

# Regenerate the bundled sample pair (deterministic).
sample: install
	$(BIN)/python scripts/make_sample.py

clean:
	rm -rf $(DEMO) .pytest_cache build *.egg-info
