# Quickstart: `make demo` and `make test`. Both create .venv and install the package first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CONTRIB := .venv-contrib

.PHONY: demo test lint bench experiments figures unseen contrib-env clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cpf-track walk_across_medium --particles 200 --seed 0 --out demo_boxes.csv --rrd demo.rrd

test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder

lint: $(STAMP)
	$(BIN)/ruff check cpf_jax kernels tests experiments notebooks
	$(BIN)/ruff format --check cpf_jax kernels tests experiments notebooks

bench: $(STAMP)
	$(BIN)/python experiments/bench_colour.py
	$(BIN)/python experiments/bench_depth.py
	$(BIN)/python experiments/bench_rgbd.py
	$(BIN)/python experiments/bench_batch.py
	$(BIN)/python experiments/bench_cascade.py
	$(BIN)/python experiments/soak.py

# Every table and figure in experiments/results (about 3 hours on a 2-core CPU; the parts
# on ../shared/data skip with a message when it is absent). Each script also runs alone.
experiments: $(STAMP) $(CONTRIB)/.installed
	$(BIN)/python experiments/colour_tables.py
	$(BIN)/python experiments/crossing_terms.py --train layout+update+mirror
	$(BIN)/python experiments/occlusion_tables.py
	$(BIN)/python experiments/depth_points.py
	$(BIN)/python experiments/depth_real.py
	$(BIN)/python experiments/cascade_points.py
	$(BIN)/python experiments/tune_colour.py
	$(BIN)/python experiments/tune_rgbd.py
	$(BIN)/python experiments/rgbd_scene.py
	$(BIN)/python experiments/unseen.py

# OpenCV's CSRT and KCF for experiments/unseen.py: opencv-contrib cannot share .venv with
# opencv-python-headless, so it gets an environment of its own.
$(CONTRIB)/.installed:
	$(PYTHON) -m venv $(CONTRIB)
	$(CONTRIB)/bin/python -m pip install --quiet opencv-contrib-python-headless numpy
	touch $(CONTRIB)/.installed

contrib-env: $(CONTRIB)/.installed

unseen: $(STAMP) $(CONTRIB)/.installed
	$(BIN)/python experiments/unseen.py

# Redraw the figures kept as data in experiments/results/*.json (no re-run).
figures: $(STAMP)
	$(BIN)/python experiments/colour_tables.py --figure-only
	$(BIN)/python experiments/bench_colour.py --figure-only
	$(BIN)/python experiments/bench_rgbd.py --figure-only
	$(BIN)/python experiments/tune_colour.py --figure-only
	$(BIN)/python experiments/tune_rgbd.py --figure-only

clean:
	rm -rf $(VENV) $(CONTRIB) build *.egg-info demo.rrd demo_boxes.csv
