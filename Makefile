# Two entry points: `make run` (main job) and `make test` (lint + full test suite).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run test lint format bench clean

setup: $(STAMP)

# torch is pinned and installed first: an unpinned torch would pull several GB of CUDA.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# The main job: about four minutes of training of the fast bearing set-up (1.3 M agent-steps, stage 3 only), then an
# evaluation of the trained policy on 20 fixed-seed stage-3 episodes.
RUN_LOGDIR := runs/make-run

run: setup
	$(BIN)/sb3-formation train --preset fast-ch5-bearing --steps 1300000 --eval-every 1000 --seed 0 --logdir $(RUN_LOGDIR)
	$(BIN)/sb3-formation evaluate "$$(ls -td $(RUN_LOGDIR)/*/ | head -n 1)" --episodes 20 --n-envs 10 --seed 0
	@echo "Training curves: tensorboard --logdir runs   (tensorboard is in $(BIN)/)"

lint: setup
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks

test: lint
	$(BIN)/python -m pytest -n 2 --durations=15 tests

format: setup
	$(BIN)/ruff format src tests benchmarks
	$(BIN)/ruff check --fix src tests benchmarks

bench: setup
	$(BIN)/python benchmarks/env_throughput.py
	$(BIN)/python benchmarks/train_throughput.py
	$(BIN)/python benchmarks/sequence_length.py

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
