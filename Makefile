# Every target is idempotent and works from a fresh clone.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# The CPU build of torch lies on local disk; installing it first keeps pip from
# resolving a multi-GB CUDA build for the torch requirement of the package.
TORCH  := torch==2.13.0

.PHONY: install test lint demo reproduce clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet $(TORCH)
	# setuptools warns about folders named like the package on every editable install of a
	# flat layout; odmv/ is the package itself, so the box says nothing here
	PYTHONWARNINGS='ignore:Editable installation' $(BIN)/pip install --quiet -e .[dev]
	touch $@

test: install
	$(BIN)/python -m pytest -q

# Renders the quickstart dataset, trains the small ODMV-Net on the CPU and evaluates it.
demo: install
	$(BIN)/python -m odmv.demo

# The paper's three experiments, the classical row and the report (resumable):
#   make reproduce PROTOCOL=mini    (2-core CPU, 12-20 h, resumable)   PROTOCOL=paper (a GPU)
#   make reproduce RETRAIN='odmvnet-*'   trains those finished rows again if their preset changed
PROTOCOL ?= mini
reproduce: install
	$(BIN)/python -m odmv.reproduce protocol=$(PROTOCOL) $(if $(RETRAIN),'retrain=[$(RETRAIN)]')

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
