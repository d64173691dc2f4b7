# Both entry points create or reuse .venv themselves.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
TSTAMP  := $(VENV)/.installed-test
OUT     ?= out

.PHONY: run bridge render experiment test install install-test peers bench clean lint

# Debian programs the tests use as independent peers: command:package. `make test` installs the
# missing ones when it can (root with apt-get, as on CI and the development machines); tests whose
# peer is missing skip with the reason.
PEERS ?= socat:socat mbpoll:mbpoll gpsd:gpsd gpspipe:gpsd-clients chromium:chromium chromedriver:chromium-driver

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[examples]'
	touch $@

$(TSTAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test,examples]'
	touch $@ $(STAMP)

install: $(STAMP)
install-test: $(TSTAMP)

# The main job: the live bridge on the default scenario (the paper's water tank) with the
# reference control stack (examples/) flying its mission over the wire; live status, then a
# summary and plots in $(OUT)/mission. RUN_ARGS="--time-scale 4" runs it 4x faster.
# MISSION_ARGS go to examples/mission.py: by default the mission ends with a surfacing phase that
# logs GNSS fixes (MISSION_ARGS= to stop at the hold).
MISSION_ARGS ?= --surface
run: $(STAMP)
	$(BIN)/python examples/demo.py --out $(OUT)/mission $(RUN_ARGS) -- $(MISSION_ARGS)

# The bridge alone, serving every device until Ctrl-C (endpoints in $(OUT)/endpoints.json).
bridge: $(STAMP)
	mkdir -p $(OUT)
	$(BIN)/hilsim run --endpoints $(OUT)/endpoints.json $(BRIDGE_ARGS)

# The paper's Fig. 4: sonar and camera frames at positions A, B, C.
render: $(STAMP)
	$(BIN)/hilsim render --at A,B,C --out $(OUT)

# The paper's water-tank experiment: drive past A, B, C; Fig. 4 and the sampling comparison.
experiment: $(STAMP)
	$(BIN)/hilsim experiment water-tank --out $(OUT)/experiment

peers:
	@need=""; for t in $(PEERS); do command -v "$${t%%:*}" >/dev/null 2>&1 || need="$$need $${t##*:}"; done; \
	if [ -n "$$need" ]; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing test peers:$$need"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$need >/dev/null \
	      || echo "warning: could not install$$need (their tests will skip)" >&2; \
	  else echo "note: missing test peers:$$need (install them with apt-get; their tests skip meanwhile)" >&2; fi; \
	fi

# The test files run on TEST_WORKERS processes (pytest-xdist; a file's tests stay together, so a
# module's bridge is started once), then the tests marked `alone` (missions, the soak, the abuse
# floods: they load both cores) one at a time. Exit status 5 is pytest's "none selected".
# TEST_WORKERS=0 runs everything in one process, in order.
TEST_WORKERS ?= 2
test: $(TSTAMP) peers
ifeq ($(TEST_WORKERS),0)
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)
else
	@rc=0; \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not alone" $(PYTEST_ARGS) || [ $$? = 5 ] || rc=1; \
	$(BIN)/python -m pytest -q -m alone $(PYTEST_ARGS) || [ $$? = 5 ] || rc=1; \
	exit $$rc
endif

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

lint: $(TSTAMP)
	$(BIN)/python -m mypy

clean:
	rm -rf $(OUT) build dist *.egg-info .pytest_cache .mypy_cache
