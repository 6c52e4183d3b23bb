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

.PHONY: install run test test-fast lint format params promote ablations bench readme push pull clean-venv

$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch==2.13.0 is the local CPU wheel (pip's find-links); requirements.lock pins the rest
	$(PY) -m pip install -q -c requirements.lock -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

# params.yaml = Hydra composition of conf/ (commit it; a test checks they agree)
params: install
	$(PY) -m pipelines.compose_params

run: install
	$(VENV)/bin/dvc repro

test: install
	$(PY) -m pytest $(PYTEST_ARGS)

# unit tests only (no stage, DAG, training run or MLflow database): under a minute
test-fast: install
	$(PY) -m pytest -m "not slow and not integration" $(PYTEST_ARGS)

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: install
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# promotion gate: challenger vs champion per registered model (after `make run`)
promote: install
	$(PY) -m pipelines.promote

# the comparisons the default run leaves out (conf/config.yaml `ablations`): DVC experiments in a
# temp copy, results collected into reports/ablations/ (the report shows them); after `make run`
ablations: install
	$(PY) -m pipelines.ablations run

bench: install
	$(PY) -m benchmarks.run

# copy reports/results_table.md (written by `make run`) into README.md
readme: install
	$(PY) -m pipelines.readme_results

# DVC remote: data and models to / from the default remote of .dvc/config (a folder beside the
# clone, ../traffictwin-dvc-store, unless `dvc remote add -d` chose another); `make pull` in a
# fresh clone restores what `make push` sent, so no stage has to run again
push: install
	$(VENV)/bin/dvc push

pull: install
	$(VENV)/bin/dvc pull

clean-venv:
	rm -rf $(VENV)
