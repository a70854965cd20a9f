# Two user-facing targets: `make demo` and `make test` (see README.md). Both bootstrap .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
export MPLBACKEND := Agg
export PYVISTA_OFF_SCREEN := true

.PHONY: demo test venv reproduce reproduce-runtime reproduce-stream reproduce-ablations accuracy-study

venv:
	@tools/bootstrap.sh $(PYTHON)

demo: venv
	@$(BIN)/python tools/demo.py

test: venv
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

# The paper's experiment on synthetic houses, on a schedule chosen to fit one 3-hour session of 2 cores with native
# bf16 together with make reproduce-stream (dense 4 / sparse 5 epochs; the committed run's steps took 76.7 min up to
# its record, docs/results-data/commands.log); `make reproduce SCALE=recipe` trains the longer dense 16 / sparse 20
# (an estimated ~3.5 h of training on 2 native-bf16 cores, ~16 h on 2 AVX2-only ones: steps x measured step times,
# docs/benchmarks.md); `make reproduce SCALE=small` is a quick check (33.5 min on a shared 2-core machine). Each run
# prints its own estimate for this machine before it starts (reproduction/estimate.py).
SCALE ?= full
reproduce: venv
	$(BIN)/python tools/reproduce.py --scale $(SCALE)

# make reproduce's steps on the accuracy study's committed weights instead of short trainings (issue 48): the train
# step trains nothing and puts pretrained:dense / pretrained:sparse (detector/pretrained, the study's plateau-trained
# dense_s0 / sparse_s0) into runs/<model>/, then eval, bench, refhead, ops, viz, curve, deploy and ablation-bench run on
# them; the bench and deploy-bench steps time 3 runs, each a process of its own (--bench-runs), whose median and
# min-max the report quotes. Full or recipe scale only (the study's dataset); both names must be committed.
reproduce-runtime: venv
	$(BIN)/python tools/reproduce.py --scale $(SCALE) --weights committed

# The paper's ablations (Sparse1+Dense23, Sparse12+Dense3, both Sparse+WideConv variants) trained and evaluated on
# the committed run's dataset, then its report again (opt in: four more trainings of the sparse model's epochs). It
# starts from the run record docs/results-data (make reproduce's record step), regenerates the dataset (refused unless
# byte for byte the recorded one) and adds the ablations to the record, so a session may train a subset
# (ABLATIONS=sparse1_dense23) and the next one the rest. docs/benchmarks.md.
ABLATIONS ?= sparse1_dense23,sparse12_dense3,sparse_wide,sparse_wide_down
reproduce-ablations: venv
	$(BIN)/python tools/reproduce.py --from-record docs/results-data --steps synth,generate,ablations,report,record --ablations $(ABLATIONS)

# Streaming AP (sAP) of make reproduce's trained models on a robot driving through held-out houses, at 768 x 512 and
# 288 x 144 under 2 and 1 threads (docs/streaming.md); `make reproduce-stream SCALE=small` is a few-minute check. The
# full scale writes its record (results JSON, commands.log, machine record) into docs/results-data/stream and
# docs/streaming.md's results block from it; `tools/reproduce_stream.py --from-record docs/results-data/stream
# --steps report` writes the block again from the record alone. The scripts are front-ends of reproduction/.
reproduce-stream: venv
	$(BIN)/python tools/reproduce_stream.py --scale $(SCALE)

# The accuracy study (issue 44; docs/results.md, "Accuracy"): restores docs/results-data/accuracy, regenerates the
# house-split dataset (refused unless it is the recorded one), trains the next unfinished training for at most
# MINUTES, tests finished ones, and writes the record and its analysis back. One session's share at a time: commit
# docs/results-data/accuracy and its summary docs/results-data/accuracy.json afterwards.
MINUTES ?= 100
accuracy-study: venv
	$(BIN)/python tools/accuracy_study.py --minutes $(MINUTES)
