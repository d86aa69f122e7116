# Every target works on a fresh machine with only Python 3.11 and pip.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check lint bench fuzz clean install

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/cvvc run

# both targets run the tests on two worker processes (pytest-xdist), each test file on one worker (its module
# fixtures made once); plain `pytest` runs them in one process
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

# the fast tier for the edit loop (< 2 minutes on 2 cores): no bus, no processes, no training on a real feeder;
# markers in pyproject.toml, tiers in docs/testing.md
check: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not bus and not process and not slow"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy schemas regression simulator_bridge training agent recordings adapters cvvc benchmarks
	@# no line cap: a module past 800 lines is a prompt to look at whether it holds two jobs (docs/architecture.md)
	@git ls-files '*.py' | xargs wc -l | awk '$$2 != "total" && $$1 > 800 {print "review: " $$2 " has " $$1 " lines"}'

bench: $(STAMP)
	$(BIN)/python -m benchmarks

# >= 20,000 hostile payloads at a live agent, bridge and recorder (IEEE 13); prints what each process counted
fuzz: $(STAMP)
	$(BIN)/python -m benchmarks.fuzz_live 20000

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
