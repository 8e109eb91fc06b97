# Quick start: `make demo` and `make test` on a fresh machine (Python 3.11). Both set up .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The rendered sample sequence bundled with the repository (models/data/samples, docs/rendering.md);
# the demo falls back to the synthetic sequence when it is absent.
SAMPLE ?= models/data/samples/shadows
DEMO_PIPELINE ?= auto

.PHONY: setup demo test lint clean bench bench-data bench-long bench-long-data

setup: $(STAMP)

# torch is installed first and pinned: this machine has the CPU build of 2.13.0 as a local file, and
# anything that asks for a newer torch would pull the multi-GB CUDA build. Then every pipeline's numba
# kernels are compiled into the cache (one process per CPU, a line per pipeline), so that no first frame
# waits for them; a kernel edited later compiles at its next first frame.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[train,data,bench,dev]'
	$(PY) -m service warm --jobs 0
	touch $(STAMP)

demo: $(STAMP)
	@if [ -d "$(SAMPLE)" ]; then input="$(SAMPLE)"; else \
		echo "bundled sample not found; using the synthetic sequence"; \
		$(PY) -m bench synthetic --out out/demo/input --size 128x96 --frames 8 --spp 8; \
		input=out/demo/input; fi; \
	$(PY) -m service denoise --pipeline $(DEMO_PIPELINE) "$$input" out/demo --png

lint: $(STAMP)
	$(PY) -m ruff check service models export bench tests

test: $(STAMP) lint haproxy
	$(PY) -m pytest

clean:
	rm -rf $(VENV) out

# Benchmark (README, "Benchmark"): every pipeline and the OIDN anchors on the bundled sample(s) plus the
# rendered sequences below; writes results.json, report.md, pareto.png and report.html to $(BENCH_OUT).
# BENCH_SCENES: models.data scenes that stress what the sample does not (disocclusion for temporal
# pipelines, fireflies, high-frequency textures); rendered once into $(BENCH_DATA), skipped when present.
# Seed 0 is the canonical animation, held out of the training set (models/data/dataset.py uses seeds 1..n).
BENCH_DATA ?= out/bench-data
BENCH_OUT ?= out/bench/report
BENCH_SCENES ?= disocclusion fireflies textures
BENCH_RENDER ?= --frames 8 --size 128x128 --spp 4 --ref-spp 512 --seed 0

# $(call render-sequences,FOLDER,SCENES,RENDER ARGS): each scene into FOLDER/scene, skipped when present
define render-sequences
	@for scene in $(2); do \
		if [ -d "$(1)/$$scene" ]; then echo "$(1): $$scene exists, skipped"; continue; fi; \
		rm -rf "$(1)/.partial-$$scene"; \
		$(PY) -m models.data render --scene $$scene $(3) --out "$(1)/.partial-$$scene" \
			&& mv "$(1)/.partial-$$scene" "$(1)/$$scene" || exit 1; \
	done
endef

bench-data: $(STAMP)
	$(call render-sequences,$(BENCH_DATA),$(BENCH_SCENES),$(BENCH_RENDER))

bench: $(STAMP) bench-data
	$(PY) -m bench run --out $(BENCH_OUT) --sequences \
		$$($(PY) -c "from models.data import SAMPLE_DIRS; print(' '.join(str(p) for p in SAMPLE_DIRS if p.is_dir()))") \
		$(addprefix $(BENCH_DATA)/,$(BENCH_SCENES))

# Long sequences (docs/benchmarks.md, "Long sequences"): crossreg from its warm start with and without online
# training, beside its pilots (crossregression), svgf and OIDN-high, over 64 frames of four scenes; the
# report adds relL2 against the frame index (curves-NAME.png). One timed pass: the online worker's timing
# varies from run to run anyway.
BENCH_LONG_DATA ?= out/bench-long-data
BENCH_LONG_OUT ?= out/bench-long/report
BENCH_LONG_SCENES ?= shadows disocclusion fireflies textures
BENCH_LONG_RENDER ?= --frames 64 --size 128x128 --spp 4 --ref-spp 256 --seed 0
BENCH_LONG_METHODS ?= crossreg crossreg:online=true,lockstep=true crossreg:min_alpha=0,pilot_bandwidth=0 crossregression svgf

bench-long-data: $(STAMP)
	$(call render-sequences,$(BENCH_LONG_DATA),$(BENCH_LONG_SCENES),$(BENCH_LONG_RENDER))

bench-long: $(STAMP) bench-long-data
	$(PY) -m bench run --out $(BENCH_LONG_OUT) --repeats 1 --no-flip --pipelines $(BENCH_LONG_METHODS) \
		--anchors oidn-high --sequences $(addprefix $(BENCH_LONG_DATA)/,$(BENCH_LONG_SCENES))

# Data set (README, "Rendering data and training"; docs/rendering.md): each models.data library scene with
# variation seeds 2..5 (0 and 1 held out), 8 frames at 128x128, 2/4/8 spp noisy input, 1024 spp references, into $(DATA_OUT)
# (git-ignored). Finished sequences are skipped, so an interrupted run resumes; a progress bar counts frames.
DATA_OUT ?= data
DATA_ARGS ?= --sequences-per-scene 4 --frames 8 --size 128x128 --spp 2 4 8 --ref-spp 1024

.PHONY: data llvm haproxy

data: $(STAMP) llvm
	$(PY) -m models.data dataset --out $(DATA_OUT)/train $(DATA_ARGS)
	$(PY) -m models.data dataset --out $(DATA_OUT)/val $(DATA_ARGS) --sequences-per-scene 1 --first-seed 6

# Mitsuba's llvm variant needs LLVM 19 (Debian: libllvm19). Best effort: installed with apt when missing and
# running as root; otherwise the renderer falls back to scalar_rgb (slower) by itself.
llvm:
	@if ls /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "llvm: installing libllvm19 for Mitsuba's llvm variant"; \
		(apt-get update -qq && apt-get install -y -qq libllvm19) \
			|| echo "llvm: apt-get install libllvm19 failed; rendering falls back to scalar_rgb"; \
	else echo "llvm: LLVM 19 not found and not installable here (needs apt and root); rendering uses scalar_rgb"; fi

# `python -m service cluster` puts HAProxy (Debian: haproxy) in front of its replicas. Best effort, like llvm:
# installed with apt when missing and running as root; otherwise the cluster test is skipped, saying why.
haproxy:
	@if command -v haproxy >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "haproxy: installing the haproxy package for python -m service cluster"; \
		(apt-get update -qq && apt-get install -y -qq haproxy) \
			|| echo "haproxy: apt-get install haproxy failed; python -m service cluster and its test need it"; \
	else echo "haproxy: not found and not installable here (needs apt and root); python -m service cluster needs it"; fi
