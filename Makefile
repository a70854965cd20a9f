# Two user-facing targets: `make demo` and `make test` (see README.md). Both bootstrap .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
export MPLBACKEND := Agg
export PYVISTA_OFF_SCREEN := true

.PHONY: demo test venv reproduce reproduce-stream

venv:
	@tools/bootstrap.sh $(PYTHON)

demo: venv
	@$(BIN)/python tools/demo.py

test: venv
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

# The paper's experiment on synthetic houses (~4.5 h on 2 cores with native bf16, ~16 h on 2 AVX2-only ones); `make reproduce SCALE=small` is a quick check (~3 min
# on 2 idle cores, several times longer on a loaded machine: 14.5 min was seen on 2 cores shared with other jobs).
SCALE ?= full
reproduce: venv
	$(BIN)/python tools/reproduce.py --scale $(SCALE)

# Streaming AP (sAP) of make reproduce's trained models on a robot driving through its houses (docs/streaming.md);
# `make reproduce-stream SCALE=small` is a few-minute check. Both scripts are front-ends of detector/reproduce/.
reproduce-stream: venv
	$(BIN)/python tools/reproduce_stream.py --scale $(SCALE)
