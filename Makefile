# traffictwin — two commands on a fresh machine:
#   make run    install into .venv (if needed), then `dvc repro` (default profile)
#   make test   install into .venv (if needed), then the whole pytest suite
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.install-stamp
export PATH := $(abspath $(VENV))/bin:$(PATH)
export PYTHONHASHSEED := 0
# the suite and the pipeline start hundreds of Python processes: let them reuse compiled bytecode
# (__pycache__, git-ignored) where the environment turns it off
unexport PYTHONDONTWRITEBYTECODE
# an extra package index for torch's CPU wheel on a machine whose pip cannot find it otherwise:
#   make install TORCH_INDEX=https://download.pytorch.org/whl/cpu
# empty (the default): pip's own configuration alone (docs/installation.md)
TORCH_INDEX ?=
# arguments of `make retrain` (python -m pipelines.retrain --help), e.g. RETRAIN_ARGS="--seed 7"
RETRAIN_ARGS ?=
# what `make reset` restores to the last commit (tracked files) and cleans (untracked, under reports/)
RESET_PATHS := params.yaml dvc.lock reports
# what `make install` imports once besides torch and Lightning, so that their bytecode is written
WARM_IMPORTS := import mlflow, mlflow.pyfunc, dvc.cli, dvc.repo, pandas, matplotlib.pyplot, cv2, \
  scipy.stats, scipy.ndimage, scipy.optimize, sklearn.metrics, hydra, pytest, xdist, fastapi, uvicorn, \
  sqlalchemy, alembic

.PHONY: install run test test-fast lint format params promote retrain reset ablations bench readme docs push pull clean-venv

$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch==2.13.0 is the CPU wheel: from pip's configuration (find-links) or TORCH_INDEX;
	# requirements.lock pins the rest
	$(PY) -m pip install -q --no-compile -c requirements.lock $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX)) -e '.[test]'
	# bytecode of what the pipeline and the suite import, written once here by importing it in two
	# processes at once (torch and Lightning | the rest), not by every process that starts first:
	# about 5,000 modules in 18 s on 2 cores, where compiling all of site-packages (pip's default,
	# or compileall) took 40 s for 17,000. A module first imported later compiles then, once
	$(PY) -c 'import torch, lightning.pytorch, torchmetrics' & warm=$$!; \
	$(PY) -c '$(WARM_IMPORTS)' && wait $$warm
	@touch $(STAMP)

install: $(STAMP)

# params.yaml = Hydra composition of conf/ (commit it; a test checks they agree)
params: install
	$(PY) -m pipelines.compose_params

# after the run, dvc.lock keeps only the stages dvc.yaml still defines (DVC never drops a removed one)
run: install
	$(VENV)/bin/dvc repro
	$(PY) -m pipelines.stage_deps prune-lock

# the whole suite on every core (pytest-xdist; the ci DAG fixture is built once and shared by the
# workers; tests marked with one xdist_group run on one worker: docs/testing.md; groups keep their
# place in the collection's order, so none that waits for the DAG is handed out before the rest),
# the 25 slowest tests listed so they stay visible
test: install
	$(PY) -m pytest -n auto --dist loadgroup --no-loadscope-reorder --durations=25 $(PYTEST_ARGS)

# the quick unit tests only (no stage, DAG, training run or MLflow database, none that took 0.5 s
# or more in tests/durations.json), on every core (pytest-xdist); how many: docs/testing.md
test-fast: install
	$(PY) -m pytest -n auto -m "not slow and not integration and not long" $(PYTEST_ARGS)

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: install
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# promotion gate: challenger vs champion per registered model (after `make run`)
promote: install
	$(PY) -m pipelines.promote

# the scheduled retraining job, once, now: new data seed -> dvc repro -> promotion gate ->
# reports/retrain_summary.{json,md} (docs/registry.md)
retrain: install
	$(PY) -m pipelines.retrain $(RETRAIN_ARGS)

# the committed workspace again after a run you do not want to keep (the Quick start's ci run):
# tracked files of $(RESET_PATHS) back to the last commit, in the workspace and in git's index
# (DVC's autostage stages dvc.lock), untracked files under reports/ removed, then data/ and
# models/ as dvc.lock says. Nothing else is touched (conf/, mlflow.db, outputs/, your files).
reset: install
	@echo "make reset: restoring $(RESET_PATHS) to the last commit (workspace and index)"
	git restore --source=HEAD --staged --worktree -- $(RESET_PATHS)
	@echo "make reset: removing untracked run outputs under reports/"
	git clean -f -d -x -- reports/
	@echo "make reset: data/ and models/ as dvc.lock says, from the DVC cache (dvc checkout --allow-missing)"
	@$(PY) -m pipelines.reset
	@st=$$(git status --short -- $(RESET_PATHS)); \
	  if [ -z "$$st" ]; then echo "make reset: done; $(RESET_PATHS) are as committed"; \
	  else echo "make reset: done; still differing from the last commit:"; echo "$$st"; fi

# the comparisons the default run leaves out (conf/config.yaml `ablations`): DVC experiments in a
# temp copy, results collected into reports/ablations/ (the report shows them); after `make run`
ablations: install
	$(PY) -m pipelines.ablations run

bench: install
	$(PY) -m benchmarks.run

# the results in reports/ (written by `make run` and `make bench`) into README.md,
# docs/results.md and docs/benchmarks.md; commit them together
readme: install
	$(PY) -m pipelines.readme_results

# every generated block of README.md and docs/: the results (make readme), the CLI reference
# (docs/cli.md) and the test counts (docs/testing.md); tests/test_readme.py and tests/test_docs.py
# fail when one is stale
docs: readme
	$(PY) -m pipelines.docs_reference

# DVC remote: data and models to / from the default remote of .dvc/config (a folder beside the
# clone, ../traffictwin-dvc-store, unless `dvc remote add -d` chose another); `make pull` in a
# fresh clone restores what `make push` sent, so no stage has to run again
push: install
	$(VENV)/bin/dvc push

pull: install
	$(VENV)/bin/dvc pull

clean-venv:
	rm -rf $(VENV)
