# make demo | make test | make lint | make bench — each sets up .venv first when needed.
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_WS ?= demo_ws

.PHONY: setup demo test lint bench clean

setup:
	@bash scripts/setup_env.sh

demo: setup
	@bash scripts/demo.sh $(DEMO_WS)

test: setup
	$(PY) -m pytest -q

lint: setup
	@VENV=$(VENV) bash scripts/lint.sh

bench: setup
	@bash scripts/bench.sh

clean:
	rm -rf $(DEMO_WS) .pytest_cache
