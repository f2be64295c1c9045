# stride_jax: `make demo` (the main job, CPU-sized) and `make test`; see README.md.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
ROBOT ?= go1
MODEL ?= stride
# Plain `make train` trains on the pendulum (minutes on a CPU); `make train ROBOT=g1` overrides.
ifeq ($(origin ROBOT),file)
TRAIN_ROBOT := pendulum
endif
PRESET ?= default

# Offline machines keep MuJoCo Menagerie beside the checkout; elsewhere the package downloads it.
ifneq ($(wildcard ../shared/menagerie),)
export MENAGERIE_ROOT ?= $(abspath ../shared/menagerie)
endif

.PHONY: setup demo data train eval table1 reproduce report ppo closed-loop test test-all test-gpu bench-sim bench-mppi gap-bench clean

$(BIN)/stride: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,warp]'
	touch $@

setup: $(BIN)/stride

## demo: the pendulum's dataset (with a summary plot), STRIDE and DeLaN trained on it, and what they
## predict near the upright against MuJoCo: runs/pendulum/phase_portrait.png and one line of
## accuracy (a few minutes on a laptop CPU)
demo: setup
	$(BIN)/stride data --robot pendulum
	$(BIN)/stride train --robot pendulum --model stride
	$(BIN)/stride train --robot pendulum --model delan
	$(BIN)/stride show

## data: one dataset, e.g. make data ROBOT=g1 PRESET=tiny
data: setup
	$(BIN)/stride data --robot $(ROBOT) --preset $(PRESET)

## train: one model, e.g. make train ROBOT=go1 MODEL=delan PRESET=tiny (generates data if absent)
train: setup
	$(BIN)/stride train --robot $(or $(TRAIN_ROBOT),$(ROBOT)) --model $(MODEL) --preset $(PRESET) --make-data

## eval: Table I metrics of trained runs, e.g. make eval ROBOT=go1 -> results/table1/go1/table.md
eval: setup
	$(BIN)/stride eval --runs 'runs/$(ROBOT)*/*'

## table1: the paper's Table I on one robot (5 models x 3 seeds; PRESET=paper wants a GPU)
table1: setup
	$(BIN)/python experiments/table1.py --robot $(ROBOT) --preset $(if $(filter default,$(PRESET)),tiny,$(PRESET))

## ppo: one PPO chunk of the warm-start policy, resumes: make ppo ROBOT=go1 PRESET=gpu MINUTES=8
ppo: setup
	$(BIN)/stride ppo --robot $(ROBOT) --preset $(PRESET) --out runs/ppo_$(ROBOT) --minutes $(or $(MINUTES),8)

## closed-loop: MPPI in closed loop in MJX -> results/closed_loop/tiny/ (PRESET=gpu: results/closed_loop/gpu/; committed runs: results/closed_loop/closed_loop_*/)
closed-loop: setup
	$(BIN)/python experiments/closed_loop.py --preset $(if $(filter default,$(PRESET)),tiny,$(PRESET))

## reproduce: the paper's figures and claims -> results/reproduce/tiny (CPU, ~8 min; PRESET=paper:
## GPU, after `make table1 PRESET=paper`)
reproduce: setup
	$(BIN)/python experiments/reproduce.py --preset $(if $(filter default,$(PRESET)),tiny,$(PRESET))

## report: results/REPORT.md from the result files on disk (paper's claims, ours, computed verdicts)
report: setup
	$(BIN)/python experiments/report.py

## test: the suite, in two pytest processes balanced by tests/durations.json (8:37-13:23 in
## clean-clone CI on this 2-core host, setup included, sessions 72-73, with durations.json
## re-recorded, the same code an hour apart; 14:42-14:51 in sessions 71-72 before the
## last cuts, 17-19 min before those; the host's speed swings by 10-20% within an hour;
## `$(BIN)/python -m pytest -q` runs it in one process); the
## tests marked slow, longer cross-checks each with a faster counterpart here, are left to test-all
test: setup
	$(BIN)/python tests/run_parallel.py

## test-all: the suite and the tests marked slow (530 s more test time measured in session 68, and
## about 330 s more marked in session 71 and 55 s in session 72, summed from their durations
## before the marks)
test-all: setup
	$(BIN)/python tests/run_parallel.py --all

## bench-sim: simulation steps/s per robot, backend and batch size -> results/throughput/bench_sim_<cpu|gpu>.md
bench-sim: setup
	$(BIN)/stride bench-sim --preset $(PRESET)

## bench-mppi: jitted MPPI step latency per robot, model, K, H -> results/mppi_latency/bench_mppi_<cpu|gpu>.md
## (on a CPU the samples are split over one XLA host device per core: STRIDE_HOST_DEVICES=auto)
bench-mppi: setup
	STRIDE_HOST_DEVICES=$${STRIDE_HOST_DEVICES:-auto} $(BIN)/stride bench-mppi --preset $(PRESET)

## gap-bench: blind benchmark of the sim-to-real gap tool -> results/gap_bench.md
## (GAP=tiny: the pendulum, ~8 min on 2 cores; GAP=default: Go1)
GAP ?= tiny
gap-bench: setup
	$(BIN)/stride gap bench --preset $(GAP) --out results

clean:
	rm -rf data/ runs/ .pytest_cache

## test-gpu: on a machine with a GPU, the kernel tests compiled and in the interpreter, the
## GPU-only checks (tests/test_gpu.py) and MJX's records on the GPU; a missing GPU fails
test-gpu: setup
	STRIDE_REQUIRE_GPU=1 $(BIN)/python -m pytest -q -p no:cacheprovider tests/test_gpu.py tests/test_fused.py tests/test_fused_step.py tests/test_record.py
