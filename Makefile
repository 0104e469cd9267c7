# make demo | make test | make lint | make bench | make docs — each sets up .venv first when needed.
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_WS ?= demo_ws

.PHONY: setup demo test lint bench docs clean

setup:
	@bash scripts/setup_env.sh

demo: setup
	@bash scripts/demo.sh $(DEMO_WS)

# one pytest worker per core (pytest-xdist): 6.6 min instead of 10.9 on 2 idle cores
test: setup
	$(PY) -m pytest -q -n auto

lint: setup
	@VENV=$(VENV) bash scripts/lint.sh

bench: setup
	@VENV=$(VENV) bash scripts/bench.sh

docs: setup
	$(PY) scripts/cli_reference.py > docs/commands.md.tmp && mv docs/commands.md.tmp docs/commands.md

clean:
	rm -rf $(DEMO_WS) .pytest_cache
