# Quick start: `make demo` and `make test` on a fresh machine (Python 3.11). Both set up .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The rendered sample sequence bundled with the repository; the demo falls back to the synthetic
# sequence when it is absent.
SAMPLE ?= models/data/samples/sample
DEMO_PIPELINE ?= bilateral

.PHONY: setup demo test lint clean

setup: $(STAMP)

# torch is installed first and pinned: this machine has the CPU build of 2.13.0 as a local file, and
# anything that asks for a newer torch would pull the multi-GB CUDA build.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[train,data,bench,dev]'
	touch $(STAMP)

demo: $(STAMP)
	@if [ -d "$(SAMPLE)" ]; then input="$(SAMPLE)"; else \
		echo "bundled sample not found; using the synthetic sequence"; \
		$(PY) -m bench synthetic --out out/demo/input --size 128x96 --frames 8 --spp 8; \
		input=out/demo/input; fi; \
	$(PY) -m service denoise --pipeline $(DEMO_PIPELINE) "$$input" out/demo --png

lint: $(STAMP)
	$(PY) -m ruff check service models export bench tests

test: $(STAMP) lint
	$(PY) -m pytest

clean:
	rm -rf $(VENV) out
