# aumesh: every entry point a user needs. `make demo` then `make test` on a fresh clone.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
UV_VERSION := 0.13.8
STAMP := $(VENV)/.installed

# Node tools (package.json / package-lock.json): three.js (inlined into release/viewer.html), vega, vega-lite and
# vega-embed (inlined into DVC's plots template) and the Khronos glTF-Validator (tests); `npm ci` installs the locked
# versions into ./node_modules (git-ignored).
TOOLS_STAMP := node_modules/.package-lock.json
# `dvc plots show/diff` draw offline with this template (.dvc/config: plots.html_template): committed, and written
# again from the locked vega packages by `make tools` (the same bytes while package-lock.json is unchanged)
PLOTS_TEMPLATE := .dvc/plots/offline.html

.PHONY: help venv tools demo refresh-demo test test-slow test-all lint lock params repro clean-build bench mlflow-server mlflow-server-postgres mlflow-ui pyfeat-check

help:
	@echo "make demo        - create .venv from requirements.lock, pull the demo data and outputs, dvc repro (up to date)"
	@echo "make refresh-demo - after a change to code, params or data: dvc repro, store the outputs in demo-remote/"
	@echo "make tools       - install the node tools (three.js for the viewer, vega for dvc plots, glTF-Validator) into node_modules/"
	@echo "make test        - run the test suite (fast tests)"
	@echo "make test-slow   - run the slow end-to-end and scale tests"
	@echo "make lint        - ruff (lint + format check) and mypy: fails on any finding (.ci/run runs it)"
	@echo "make lock        - re-resolve requirements.lock from pyproject.toml"
	@echo "make params      - recompose params.yaml from conf/ (what dvc exp run does)"
	@echo "make bench       - run the benchmarks under benchmarks/"
	@echo "make mlflow-server - start an MLflow tracking server (SQLite backend) on 127.0.0.1:5000"
	@echo "make mlflow-server-postgres - a team's tracking server: MLFLOW_DB=postgresql://USER@DBHOST/DB MLFLOW_HOST=0.0.0.0"
	@echo "make cluster     - start a local Dask cluster (a scheduler + CLUSTER_WORKERS workers on 127.0.0.1:CLUSTER_PORT); make cluster-stop"
	@echo "make pyfeat-check - py-feat's own client on release/ and releases/<family>/ (throwaway venv with py-feat + torch, ~6.5 GB; PYFEAT_VENV=DIR keeps one)"

# The environment: a fresh venv, exact pins from requirements.lock, then the package itself without deps.
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check uv==$(UV_VERSION)
	$(BIN)/uv pip sync --quiet --compile-bytecode --python $(BIN)/python requirements.lock
	$(BIN)/uv pip install --quiet --python $(BIN)/python --no-deps -e .
	touch $(STAMP)

venv: $(STAMP)

$(TOOLS_STAMP): package.json package-lock.json
	npm ci --no-audit --no-fund --loglevel=error
	touch $(TOOLS_STAMP)

$(PLOTS_TEMPLATE): $(TOOLS_STAMP) $(STAMP) src/aumesh/export/dvc_plots.py
	$(BIN)/python -m aumesh dvc-plots-template --out $@

tools: $(TOOLS_STAMP) $(PLOTS_TEMPLATE)

lock:
	$(BIN)/uv pip compile pyproject.toml --extra test --extra dev --extra s3 --python-version 3.11 --python-platform x86_64-manylinux_2_28 -o requirements.lock

# After a change that reruns stages: rebuild, store the outputs in the committed demo remote, drop objects
# the workspace no longer uses (older commits keep theirs in their own demo-remote/); then commit
# dvc.lock, metrics/ and demo-remote/ together. Run it on a committed tree: the release records the git
# commit and whether the tree was dirty.
refresh-demo: $(STAMP) $(TOOLS_STAMP)
	$(BIN)/dvc repro
	$(BIN)/dvc push --quiet --remote demo
	# build/prepared is `push: false` (dvc.yaml; ~57 GB at 10M frames); the demo's (26 MB) goes into the demo remote
	# all the same, so that a fresh clone's `make demo` finds every stage up to date
	$(BIN)/python scripts/push_unpushed.py demo-remote build/prepared
	$(BIN)/dvc gc --workspace --all-experiments --cloud --remote demo --force --quiet
	git add dvc.lock metrics demo-remote
	@echo "now commit dvc.lock, metrics/ and demo-remote/ (staged)"

params: $(STAMP)
	$(BIN)/aumesh compose-params

# The demo remote holds the tables and the outputs of the committed dvc.lock: `dvc pull` fetches both and
# `dvc repro` finds everything up to date, so a fresh clone stays clean (README "A clean clone stays clean").
# --allow-missing: outputs the remote lacks (a stale dvc.lock) are rebuilt by `dvc repro` instead.
demo: $(STAMP) $(TOOLS_STAMP)
	$(BIN)/dvc pull --quiet --allow-missing
	$(BIN)/dvc repro
	@echo
	@echo "Release written to $(CURDIR)/release/:"
	@ls -1 release
	@$(BIN)/python -c "import json; c=json.load(open('release/model_card.json')); print('CV R2 = %.4f +/- %.4f  (folds %s), MAE = %.4f' % (c['cv']['r2_mean'], c['cv']['r2_std'], c['cv']['r2_folds'], c['cv']['mae_mean']))"

# The tests' Python processes (pytest's workers and every `aumesh`, `dvc` and `mlflow` a test starts) cache their
# bytecode, Python's default, even where the shell sets PYTHONDONTWRITEBYTECODE (as CI's does): without the cache each
# worker rewrote every test module's asserts and each process compiled aumesh again (~2 s per worker). The caches are
# __pycache__/ folders, which git ignores.
PYTEST := PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest

test: $(STAMP) $(TOOLS_STAMP)
	$(PYTEST) -q -n auto

# The checks .pre-commit-config.yaml runs on each commit, over the whole tree; settings in pyproject.toml.
# `ruff format .` and `ruff check --fix .` repair most findings.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test-slow: $(STAMP) $(TOOLS_STAMP)
	$(PYTEST) -q -m slow

test-all: $(STAMP) $(TOOLS_STAMP)
	$(PYTEST) -q -m "slow or not slow"

repro: $(STAMP) $(TOOLS_STAMP)
	$(BIN)/dvc repro

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_engine_vs_sklearn.py
	$(BIN)/python benchmarks/bench_scaling.py

MLFLOW_PORT ?= 5000
mlflow-server: $(STAMP)
	@echo "the runs, best r2_mean first: http://127.0.0.1:$(MLFLOW_PORT)/#/experiments/1/runs?workflowType=machine_learning&viewStateShareKey=aumesh-runs"
	@echo "(1 = the id of experiment aumesh in a clone's own store; see the README, section Tracking)"
	$(BIN)/mlflow server --backend-store-uri sqlite:///$(CURDIR)/mlflow.db --host 127.0.0.1 --port $(MLFLOW_PORT)

# A team's tracking server (README "Working as a team"): PostgreSQL backend, artifacts served through the server.
# Clients: MLFLOW_TRACKING_URI=http://HOST:$(MLFLOW_PORT) or `tracking: {tracking_uri: ...}` in aumesh.local.yaml.
# The password comes from ~/.pgpass or PGPASSWORD (libpq), never the command line.
MLFLOW_DB ?= postgresql://mlflow@localhost:5432/mlflow
MLFLOW_HOST ?= 127.0.0.1
MLFLOW_ARTIFACTS ?= $(CURDIR)/mlflow-server-artifacts
mlflow-server-postgres: $(STAMP)
	$(BIN)/aumesh server --backend-store-uri '$(MLFLOW_DB)' --artifacts-destination '$(MLFLOW_ARTIFACTS)' \
		--host $(MLFLOW_HOST) --port $(MLFLOW_PORT)

clean-build:
	rm -rf build release

# A local Dask cluster (README "Scale out"): `dask scheduler` and CLUSTER_WORKERS `dask worker` processes on 127.0.0.1,
# started in CLUSTER_CWD, a folder outside the repository (the stages hand the workers absolute paths, so any number of
# workspaces of this machine share it); pid files and logs in .cluster/ (git-ignored). Use it with
# `AUMESH_COMPUTE_ADDRESS=tcp://127.0.0.1:8786 dvc repro -f` (params.yaml stays as it is).
.PHONY: cluster cluster-stop
CLUSTER_PORT ?= 8786
CLUSTER_WORKERS ?= 2
CLUSTER_THREADS ?= 1
CLUSTER_CWD ?= $(or $(TMPDIR),/tmp)
CLUSTER_STATE := $(CURDIR)/.cluster
CLUSTER_ADDRESS := tcp://127.0.0.1:$(CLUSTER_PORT)

cluster: $(STAMP)
	@mkdir -p "$(CLUSTER_STATE)"
	@if [ -s "$(CLUSTER_STATE)/scheduler.pid" ] && kill -0 "$$(cat "$(CLUSTER_STATE)/scheduler.pid")" 2>/dev/null; then \
		echo "a cluster is running already (pid $$(cat "$(CLUSTER_STATE)/scheduler.pid")): make cluster-stop first"; exit 1; fi
	@cd "$(CLUSTER_CWD)" && { nohup "$(CURDIR)/$(BIN)/dask" scheduler --host 127.0.0.1 --port $(CLUSTER_PORT) \
		--no-dashboard > "$(CLUSTER_STATE)/scheduler.log" 2>&1 & echo $$! > "$(CLUSTER_STATE)/scheduler.pid"; }
	@cd "$(CLUSTER_CWD)" && for i in $$(seq 1 $(CLUSTER_WORKERS)); do \
		{ ARROW_DEFAULT_MEMORY_POOL=system nohup "$(CURDIR)/$(BIN)/dask" worker $(CLUSTER_ADDRESS) --host 127.0.0.1 \
			--nthreads $(CLUSTER_THREADS) --no-dashboard > "$(CLUSTER_STATE)/worker-$$i.log" 2>&1 & \
		  echo $$! > "$(CLUSTER_STATE)/worker-$$i.pid"; }; done
	@$(BIN)/python -c "from distributed import Client; c = Client('$(CLUSTER_ADDRESS)', timeout=60); \
		c.wait_for_workers($(CLUSTER_WORKERS), timeout=120); c.close()" 2>/dev/null \
		|| { echo "the cluster did not start: see $(CLUSTER_STATE)/*.log"; $(MAKE) --no-print-directory cluster-stop; exit 1; }
	@echo "Dask cluster at $(CLUSTER_ADDRESS): $(CLUSTER_WORKERS) workers x $(CLUSTER_THREADS) threads, started in $(CLUSTER_CWD)"
	@echo "use it:  AUMESH_COMPUTE_ADDRESS=$(CLUSTER_ADDRESS) dvc repro -f     (stop it: make cluster-stop)"

cluster-stop:
	@for f in "$(CLUSTER_STATE)"/worker-*.pid "$(CLUSTER_STATE)/scheduler.pid"; do \
		[ -s "$$f" ] || continue; pid=$$(cat "$$f"); \
		if kill "$$pid" 2>/dev/null; then \
			for _ in $$(seq 50); do kill -0 "$$pid" 2>/dev/null || break; sleep 0.2; done; \
			echo "stopped $$(basename "$$f" .pid) (pid $$pid)"; fi; \
		rm -f "$$f"; done

# Sweeps (README "Sweeps and promotion"): the demo grid in-process, the latest sweep's table, promotion.
.PHONY: sweep runs promote
SWEEP_GRID ?= preprocess.target=absolute,neutral,within features=au,au_pose,au_pose_interactions model.n_components=10,23,40,83
sweep: $(STAMP)
	$(BIN)/aumesh sweep -m $(SWEEP_GRID)

# bare, as a user types them: this clone's latest sweep; `promote` refuses to overrule a newer evaluate run of this
# clone (`aumesh promote --latest` is the explicit way past that refusal, never make's)
runs: $(STAMP)
	$(BIN)/aumesh runs

promote: $(STAMP)
	$(BIN)/aumesh promote
	@echo "now: make repro   (dvc repro rebuilds the promoted release)"

# py-feat's own loader and plot_face_mesh on the release (optional, slow: py-feat pulls torch).
pyfeat-check: $(STAMP)
	$(BIN)/python scripts/check_pyfeat_client.py --release release/au_to_mesh_pls.npz --out build/pyfeat-check \
		$(if $(wildcard releases/blendshapes/bs_to_mesh_pls.npz),--blendshape-release releases/blendshapes/bs_to_mesh_pls.npz) \
		$(if $(wildcard releases/emotions/emotion_to_mesh_pls.npz),--emotion-release releases/emotions/emotion_to_mesh_pls.npz) \
		$(if $(PYFEAT_VENV),--venv $(PYFEAT_VENV))
