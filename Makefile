# posediff — every target but `install` uses the virtual environment in .venv/.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON_BOOT ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libgles2

help: ## list the targets
	@grep -E '^[a-zA-Z_-]+:.*?## .*$$' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  \033[36m%-14s\033[0m %s\n", $$1, $$2}'

install: system-deps $(VENV)/bin/activate ## create .venv and install posediff editable with its dev extras
	$(PY) -m pip install --disable-pip-version-check -q -e '.[dev]'
	$(VENV)/bin/posediff --help > /dev/null
	@echo "posediff installed in $(VENV)"

$(VENV)/bin/activate:
	$(PYTHON_BOOT) -m venv $(VENV)

system-deps: ## Mesa's EGL for offscreen rendering (apt, as root; skipped with a note otherwise)
	@if [ "$$(id -u)" = "0" ] && command -v apt-get > /dev/null; then \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get install -y -q --no-install-recommends $(APT_PACKAGES) > /dev/null 2>&1 \
	  || { apt-get update -q > /dev/null && apt-get install -y -q --no-install-recommends $(APT_PACKAGES) > /dev/null; }; \
	  echo "system packages present: $(APT_PACKAGES)"; \
	else \
	  echo "note: not root or no apt-get; make sure these are installed: $(APT_PACKAGES)"; \
	fi

test: ## the default test suite (not slow, not gpu)
	$(PY) -m pytest -q

test-all: ## every test, slow ones included
	$(PY) -m pytest -q -m "not gpu"

demo: ## render a small SYMSOL-T, train `quickstart` on the CPU, evaluate, predict (≈16 min on 2 cores; outputs/demo/; progress in outputs/demo.partial/fit/progress.log)
	$(VENV)/bin/posediff demo trainer.enable_progress_bar=false

walkthrough: ## the Lie group walk-through (notebooks/01) in full mode; figures in outputs/walkthrough/
	$(VENV)/bin/posediff groups
	POSEDIFF_FAST=0 POSEDIFF_NOTEBOOK_OUT=outputs/walkthrough MPLBACKEND=Agg $(PY) notebooks/01_lie_groups.py

figures: ## regenerate the README figures (docs/images/)
	POSEDIFF_FAST=0 POSEDIFF_NOTEBOOK_OUT=docs/images MPLBACKEND=Agg $(PY) notebooks/01_lie_groups.py
	POSEDIFF_FAST=0 POSEDIFF_NOTEBOOK_OUT=docs/images MPLBACKEND=Agg $(PY) notebooks/04_bop.py
	$(VENV)/bin/posediff data grid out=docs/images/symsolt_grid.png

bench: ## time the Lie group ops against peer libraries (writes benchmarks/results/lie_ops.json)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/lie_ops.py

bench-tuned: ## the same with glibc keeping large blocks (writes benchmarks/results/lie_ops_tuned_malloc.json)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/lie_ops.py --tuned-malloc

toy: ## the symmetric-shape toy, every ablation variant (~2.5 h on one core; writes benchmarks/results/toy.json, toy.md)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/toy.py

learning-speed: ## what makes orientation learn soonest on a CPU: 11 variants × 1000 steps (≈ 1 h, 2 at a time; writes benchmarks/results/learning_speed.json, .md)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/learning_speed.py --parallel 2

pretrain: ## posediff pretrain: the encoder by symmetry-aware regression on the 128 px renders (writes data/pretrained/symsolt_resnet18_crop64.pt)
	$(VENV)/bin/posediff data render dataset=symsolt split=train image_size=128 out=data/symsolt_scene2_cpu128 progress=false
	$(VENV)/bin/posediff data render dataset=symsolt split=test image_size=128 out=data/symsolt_scene2_cpu128 progress=false
	$(VENV)/bin/posediff pretrain trainer.enable_progress_bar=false

bench-render: ## SYMSOL-T rendering speed vs a training step (writes benchmarks/results/render.json)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/render.py

bench-train: ## one training step split by phase, and each speed lever (writes benchmarks/results/train_step.json)
	$(PY) benchmarks/train_step.py

bench-sampler: ## time per denoising step, network vs group math (writes benchmarks/results/sampler.json)
	OMP_WAIT_POLICY=PASSIVE $(PY) benchmarks/sampler.py

notebooks: ## run the notebooks in fast mode
	$(PY) -m pytest -q -m notebooks tests/test_notebooks.py

gpu-check: ## the one GPU check (benchmarks/gpu_check.py, ≤ 8 min): JSON + table in benchmarks/results/gpu_check_<gpu>.*
	$(PY) benchmarks/gpu_check.py

lint: ## ruff check + format check + mypy (lie/, diffusion/, symmetry, metrics/; pyproject [tool.mypy])
	$(PY) -m ruff check src tests benchmarks notebooks
	$(PY) -m ruff format --check src tests benchmarks notebooks
	$(PY) -m mypy

clean: ## remove caches and outputs (keeps .venv)
	rm -rf .pytest_cache outputs multirun build dist
	find . -name __pycache__ -type d -prune -exec rm -rf {} +

.PHONY: help install system-deps test test-all demo walkthrough figures bench bench-tuned bench-render bench-train learning-speed pretrain notebooks gpu-check lint clean
