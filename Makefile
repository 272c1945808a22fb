# thinshell: two commands on a fresh machine.
#   make demo   set up (venv + install) and run the main job on the bundled scene and bag
#   make test   set up and run the test suite (not the slow tests; two workers)
# The venv's interpreter: the distribution's /usr/bin/python3.11 where there is one, else python3
# (`make setup PYTHON=...` picks another). Debian's is linked statically against libpython; a
# shared-library build (pyenv's, `--enable-shared`) runs the Newton loop's Python glue about 10 %
# slower (Forming bench, docs/benchmarks_log.md 2026-11-23). Where it cannot make a venv (no venv
# module), set-up falls back to python3.
SYSTEM_PYTHON := $(wildcard /usr/bin/python3.11)
PYTHON ?= $(if $(SYSTEM_PYTHON),$(SYSTEM_PYTHON),python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-slow bench setup clean

setup: $(STAMP)

$(STAMP): requirements.txt setup.py package.xml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || { echo "thinshell: $(PYTHON) cannot make a venv; using python3"; rm -rf $(VENV); python3 -m venv $(VENV); }
	$(PY) -m pip install --upgrade --quiet pip
	@echo "thinshell: installing the dependencies into $(VENV) (first run only; about 1-3 min with a warm pip cache)"
	$(PY) -m pip install --progress-bar on -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	@echo "thinshell: compiling the simulator's kernels into Taichi's offline cache (first set-up only; about 1-4 min)"
	$(PY) -m thinshell_ros.cli compile
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m thinshell_ros.cli demo

# make test: two pytest-xdist workers (CI has 2 cores), each test module whole on one worker (its
# module-scoped fixtures built once), modules handed out in collection order with the `early` ones
# first (tests/conftest.py); then the `realtime` tests (wall-clock timing) in one process, with the
# machine to themselves. Both parts run; the target fails if either does. `pytest tests` alone runs
# everything serially.
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow and not realtime" -n 2 --dist loadfile --no-loadscope-reorder tests; \
	status=$$?; $(PY) -m pytest -q -m "realtime and not slow" tests || status=1; exit $$status

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow tests

bench: $(STAMP)
	$(PY) -m thinshell_ros.cli bench forming --json

clean:
	rm -rf $(VENV) build install log *.egg-info
