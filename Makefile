# The two commands of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR := out/demo

.PHONY: setup system-deps demo fleet-demo lint test test-long bench install-wireshark clean tsharks golden captures fuzz-self install-profile lua-tables wheel

setup: system-deps $(STAMP)

system-deps:
	@bash scripts/setup-system.sh

# (pip compiles what it installs one file after another: 20 of its 45 s; compileall on every core
# makes the same bytecode in 13. A file it cannot compile is compiled, or refused, when imported.)
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip==24.3.1
	$(PY) -m pip install -q --no-compile -r requirements.lock
	$(PY) -m compileall -q -j 0 "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" > /dev/null || true
	$(PY) -m pip install -q --no-deps -e .
	@touch $@

# The main job: analyse a bundled capture (5 % loss, duplicates, reordering) into the terminal
# summary, a JSON and an HTML report.
demo: setup
	@mkdir -p $(DEMO_DIR)
	$(VENV)/bin/vm110 analyze captures/loss.pcapng --json $(DEMO_DIR)/report.json --html $(DEMO_DIR)/report.html
	@echo "reports: $(DEMO_DIR)/report.json $(DEMO_DIR)/report.html"

# A synthetic fleet (10 machines at 4 sites, 4 captures each; bad links, failing commands, a capture
# cut short) built into a dataset, queried and reported. Run again: nothing is analysed twice.
FLEET_DIR := out/fleet-demo
fleet-demo: setup
	$(PY) -m vm110.fleet.demo $(FLEET_DIR)
	$(VENV)/bin/vm110 fleet build $(FLEET_DIR)/sites --meta 'sites/{site}/{machine}/*.pcap' --out $(FLEET_DIR)/dataset \
		|| [ $$? -eq 2 ]   # (2: the damaged capture the demo plants on purpose)
	$(VENV)/bin/vm110 fleet query $(FLEET_DIR)/dataset --worst links
	$(VENV)/bin/vm110 fleet query $(FLEET_DIR)/dataset --named watchdog
	$(VENV)/bin/vm110 fleet query $(FLEET_DIR)/dataset --worst commands
	$(VENV)/bin/vm110 fleet query $(FLEET_DIR)/dataset --trend jitter --by week
	$(VENV)/bin/vm110 fleet report $(FLEET_DIR)/dataset --html $(FLEET_DIR)/report.html
	@echo "report: $(FLEET_DIR)/report.html"

# Code health: ruff (rules in pyproject.toml), mypy on the package (its [tool.mypy]), luacheck on the
# dissector (with the repo's .luacheckrc when there is one, never a config found above the repo).
LINT_PY := pcap_tools tests scripts/fuzz-self scripts/lua-tables bench
LUACHECK_CONFIG := $(if $(wildcard .luacheckrc),--config .luacheckrc,--no-config)
lint: setup
	@status=0; \
	$(VENV)/bin/ruff check --no-cache $(LINT_PY) || status=1; \
	$(PY) -m mypy || status=1; \
	luacheck --no-color $(LUACHECK_CONFIG) dissector || status=1; \
	exit $$status

# (Bytecode compiled once: the suite starts some hundreds of interpreters, and under
# PYTHONDONTWRITEBYTECODE each would compile the package again, about 0.15 s.)
# Workers: half again the cores. A third of the suite's time is spent waiting (fuzzed controllers'
# timeouts, simulators' timers, subprocesses): on 2 cores, 2 workers kept them about 70 % busy
# (914 s), 3 workers 93 % (675 s). --dist worksteal: a worker that has run out takes tests queued
# for a busy one, so that a file's slow tests at the end do not finish the run alone. The log ends
# with the 20 slowest tests: the suite must stay within 15 minutes on 2 cores.
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 2); echo $$(( n + (n + 1) / 2 )))
test: setup tsharks lint
	$(PY) -m compileall -q -j 0 pcap_tools tests > /dev/null
	$(PY) -m pytest -n $(TEST_WORKERS) --dist worksteal -q --durations=20

# Long runs kept out of `make test` (e.g. the fuzzer against the reference controller for 60 s).
test-long: setup
	VM110_LONG_TESTS=1 $(PY) -m pytest -n $(TEST_WORKERS) -q -m slow

# Soak run of the self-fuzzer (tests/selffuzz): mutated bundled captures through decode, analyze (both
# engines) and the dissector on every tshark; failing inputs kept in out/fuzz-self/ with a .txt each.
FUZZ_SELF_SECONDS ?= 600
fuzz-self: setup tsharks
	FUZZ_SELF_SECONDS=$(FUZZ_SELF_SECONDS) $(PY) scripts/fuzz-self

bench: setup tsharks
	@set -e; for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b; done

# The synthesised part of captures/ (each with its .truth.json; see captures/README.md).
CAPTURES := normal.pcap disarmed.pcap loss.pcapng retransmit.pcap vrco.pcap vrpo-split.pcapng illegal.pcap \
	bu-watchdog.pcap controller-watchdog.pcap glink.pcapng overlap.pcapng bu-stops.pcap restart.pcapng
captures: setup
	@set -e; for c in $(CAPTURES); do $(VENV)/bin/vm110 synth "$${c%.*}" --seed 1 --out "captures/$$c"; done
	$(PY) captures/crane.py captures/crane.pcapng

# The dissector is tested on tshark 4.0 (Lua 5.2), 4.4 and 4.6 (Lua 5.4): the host's tshark stands
# for its own version when it loads Lua plugins for this user, and each other version runs in a
# cached Debian chroot (bookworm, trixie, forky) built here (tests/tshark_runner.py decides which).
tsharks: setup
	@$(PY) tests/tshark_runner.py --setup

# Regenerate the dissector's `tshark -V -O vm110` goldens (tests/golden/), one per tshark version.
golden: setup tsharks
	$(PY) tests/test_dissector_golden.py

# The dissector's field, enum and layout tables from the Python declaration (vm110/protocol.py).
lua-tables: setup
	$(PY) scripts/lua-tables

# The plugin (and the VM-110 profile: columns, filter buttons, colouring rules) where this user's
# Wireshark looks, as `tshark -G folders` reports it: `vm110 wireshark install` (README, "Installing").
# Files are replaced atomically; the user's own files in those folders are left alone.
# Only the command is needed (it finds tshark's folders, or takes Wireshark's defaults without one):
# not the test tools that setup installs through apt and sudo.
install-wireshark: $(STAMP)
	$(VENV)/bin/vm110 wireshark install

install-profile: $(STAMP)
	$(VENV)/bin/vm110 wireshark install --profile

# dist/vm110-<version>-py3-none-any.whl: the package with the plugin, the profile, the examples and the
# report schema inside (setup.py), built offline with the pinned setuptools; `pipx install` takes it.
wheel: setup
	$(PY) -m pip wheel --no-deps --no-build-isolation -w dist .

clean:
	rm -rf $(VENV) out dist build .pytest_cache .hypothesis
