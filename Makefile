# One command sets up and measures, one sets up and tests (README quick start).
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
APT_PACKAGES := libusb-1.0-0 libgl1 libgomp1 chromium chromium-driver systemd
NODE_APT_PACKAGES := nodejs npm

.PHONY: measure test test-fast system-deps clean

CELL_CONFIG := config/sim-cell.toml
CALIBRATION := out/calibration.json

# The paper's workflow: calibrate the scanner on its target (hand-eye, docs/calibration.md), plan the whole
# default part (docs/planning.md) into out/plan.toml, then measure it on the simulated cell with the calibrated
# mounts (job.installation_source = "calibration"). A calibration newer than the cell configuration and the
# installed package is reused.
measure: $(STAMP) $(CALIBRATION)
	$(VENV)/bin/tandemscan plan --out out/plan.toml --png out/plan.png
	$(VENV)/bin/tandemscan measure --plan out/plan.toml --calibration $(CALIBRATION)

$(CALIBRATION): $(CELL_CONFIG) $(STAMP)
	$(VENV)/bin/tandemscan calibrate --out $(CALIBRATION)

# Two workers (CI has two cores; many tests wait on processes and sockets), a test file to a worker so that a
# module's shared job runs once (docs/testing.md).
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The inner loop (docs/testing.md, the inner loop): the suite without the HIL cell, Chromium, whole jobs (tests/e2e/)
# and the tests marked slow (about a minute on 2 idle cores).
test-fast: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not hil and not browser and not e2e and not slow"

# System packages, installed through apt only where missing: what Open3D needs at import time, Chromium for the
# report rendering test and, with chromium-driver, the console's browser tests; systemd for the unit tests
# (systemd-analyze verify, sysusers, tmpfiles); Node.js and npm for node-opcua, the independent OPC UA client of
# tests/daemon/test_opcua.py (installed from tests/node/package-lock.json), only where no npm is on the PATH (a NodeSource
# nodejs carries its own npm and conflicts with Debian's).
system-deps:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	command -v npm >/dev/null 2>&1 || missing="$$missing $(NODE_APT_PACKAGES)"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

# torch is pinned first to the CPU build so that the generic requirement does not pull a CUDA build.
$(STAMP): pyproject.toml tests/node/package-lock.json | system-deps
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "$(PYTHON) not found: install Python 3.11"; exit 2; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	npm ci --prefix tests/node --no-audit --no-fund --loglevel=error
	touch $(STAMP)

clean:
	rm -rf $(VENV) out tests/node/node_modules
