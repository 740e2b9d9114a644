# The two quick-start commands: `make demo` and `make test`.
# Both create .venv and install the project into it on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow test-viewer lint bench install clean compose-file compose-ci

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip setuptools
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# The paper's fleet as separate processes (router, target, 3 SITL, 3 agents, ground station),
# then the paper's figures from its recording.
demo: $(STAMP)
	rm -rf runs/demo
	$(BIN)/fleetmpc up scenarios/paper.toml --run-dir runs/demo
	$(BIN)/fleetmpc report runs/demo/run.rrd --out runs/demo/report

# The layer contracts (pyproject.toml's [tool.importlinter]) read fleetmpc as one folder: a view
# of links made from its package-dir mapping.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python tools/import_view.py build/import-view
	cd build/import-view && $(abspath $(BIN))/lint-imports --no-cache $(CURDIR)/pyproject.toml

test: lint
	$(BIN)/python -m pytest -q

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

# Recordings as a user sees them: Rerun's web viewer in headless Chromium (installed from
# Debian's packages when missing; needs root).
test-viewer: $(STAMP)
	command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium)
	$(BIN)/python -m pytest -q -m viewer

bench: $(STAMP)
	$(BIN)/pip install --quiet -e '.[bench]'
	$(BIN)/fleetmpc bench scenarios/paper.toml

# docker/compose.yaml is `fleetmpc compose scenarios/paper.toml`; compose-file regenerates it.
compose-file: $(STAMP)
	$(BIN)/fleetmpc compose scenarios/paper.toml -o docker/compose.yaml

# The paper fleet under docker compose on a private Docker daemon, with the gates, and a check of
# a generated 5-vehicle file (needs root; installs docker.io and mmdebstrap). Outputs: runs/compose-ci.
compose-ci: $(STAMP)
	rm -rf runs/compose-ci && mkdir -p runs/compose-ci
	$(BIN)/fleetmpc keys scenarios/paper.toml -o runs/compose-ci/secrets
	$(BIN)/fleetmpc keys scenarios/wedge-circle.toml -o runs/compose-ci/wedge-secrets
	$(BIN)/fleetmpc compose scenarios/wedge-circle.toml -o runs/compose-ci/wedge-circle.yaml \
		--secrets-dir-var WEDGE_SECRETS --secrets-dir wedge-secrets
	FLEETMPC_SECRETS=$(abspath runs/compose-ci/secrets) PYTHON=$(abspath $(BIN)/python) \
		docker/ci.sh docker/compose.yaml runs/compose-ci --gates \
		--config-only runs/compose-ci/wedge-circle.yaml

clean:
	rm -rf $(VENV) runs build .pytest_cache .ruff_cache
