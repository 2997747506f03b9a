# facepipe: `make demo` runs the whole pipeline on the built-in sample rig, `make test` the tests.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
FP     := $(BIN)/facepipe
DEMO   := demo

.PHONY: venv demo test test-fast bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

venv: $(VENV)/.installed

demo: venv
	rm -rf $(DEMO)
	$(FP) sample $(DEMO)/rig
	$(FP) fit $(DEMO)/rig/sample.toml -o $(DEMO)/fit.npz
	$(FP) bake $(DEMO)/fit.npz -o $(DEMO)/model.npz
	$(FP) replay $(DEMO)/rig/take.csv -m $(DEMO)/model.npz -o $(DEMO)/replay --save-large-scale
	$(FP) export $(DEMO)/replay --format obj -o $(DEMO)/obj
	$(FP) eval $(DEMO)/replay --truth $(DEMO)/rig/take_truth.npz --large-scale
	$(FP) preview $(DEMO)/replay --truth $(DEMO)/rig/take_truth.npz -o $(DEMO)/preview.png
	$(FP) preview $(DEMO)/replay --truth $(DEMO)/rig/take_truth.npz --size 300 --movie $(DEMO)/replay.mp4
	@echo "done: open $(DEMO)/replay.mp4 (the replay as a movie) and $(DEMO)/preview.png; commands: $(FP) --help"

test: venv
	$(BIN)/python -m pytest -q -ra

# the unit tests alone: no ICT kit, no end-to-end pipeline runs (a fraction of `make test`)
test-fast: venv
	$(BIN)/python -m pytest -q -m "not ict and not slow"

# the paper's configuration: ~530k vertices, 89 markers on the shell, 6 example poses (a few minutes);
# then `facepipe batch` of 32 sample-rig takes on a LocalCluster of 2 workers against one
# `facepipe replay` per take (bench/batch.json, several minutes); then appearance classification on
# rendered ICT footage (bench/appearance_ict.json, a few minutes, where the kit is beside the checkout)
bench: venv
	$(BIN)/python -m bench.paper_scale -o bench/results.json --vertices 530000 --markers 89 --examples 6 --frames 128 --bake-repeats 5
	@# where the fused kernel's stages spend their time: the stage table for builds with one part taken out
	$(BIN)/python -m bench.kernel_variants --work bench/work --json bench/kernel_variants.json
	$(BIN)/python -m bench.point_caches_speed --frames 128 --json bench/point_caches_speed.json
	@# the host's share of a marker replay: cleaning and the novelty gate's fits, ms a frame (ICT takes where the kit is here)
	$(BIN)/python -m bench.host_stages --json bench/host_stages.json
	$(BIN)/python -m bench.batch_speed -o bench/batch.json --takes 32 --frames 200 --workers 2
	@# appearance classification (8 regions) on rendered ICT footage: needs the kit in ../shared
	if [ -d ../shared/data/ict ]; then $(BIN)/python -m bench.appearance_ict --out bench/work/appearance --json bench/appearance_ict.json; \
	else echo "bench.appearance_ict skipped: the ICT kit (../shared/data/ict) is not here"; fi

clean:
	rm -rf $(DEMO) bench/results.* bench/batch.json bench/work .pytest_cache
