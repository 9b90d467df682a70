# Set-up and the two everyday jobs. `make test` and `make suite` each do all the set-up on a fresh
# machine: a virtual environment in .venv with torch's CPU build (never the multi-GB CUDA download).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup test test-fast suite lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@# socat's linked ptys stand in for a USB-serial cable in the tests (Debian's package; needs root)
	command -v socat >/dev/null || (apt-get update -qq && apt-get install -y -qq socat) \
		|| echo "warning: install socat (apt-get install socat) for the serial-adapter test"
	@# a headless Chromium opens the live view's page in its tests (Debian's package; needs root)
	command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium) \
		|| echo "warning: install chromium (apt-get install chromium) for the live view's browser test"
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[all]"
	@# the project's own bytecode, once: pip compiles what it installs but not an editable install's
	@# sources, and where PYTHONDONTWRITEBYTECODE is set (as in many container images) every process would
	@# compile them again in memory (about 0.1 s a start; the tests start hundreds of processes)
	$(PY) -m compileall -q hil emulator policies
	touch $(STAMP)

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

# the wall-clock tests after the rest, one at a time: beside another test worker a real-time loop on
# this size of machine (2 cores) falls behind, and they would fail saying so
test: lint
	$(VENV)/bin/pytest -n 2 -q tests scenarios -m "not realtime"
	$(VENV)/bin/pytest -q tests scenarios -m realtime

# everything but the slow, the learning code's and the wall-clock tests (pytest markers, pyproject.toml)
test-fast: lint
	$(VENV)/bin/pytest -n 2 -q tests scenarios -m "not slow and not learning and not realtime"

suite: setup
	$(VENV)/bin/hil suite scenarios/ --out reports/

clean:
	rm -rf $(VENV) reports .pytest_cache .ruff_cache
