# thinshell: two commands on a fresh machine.
#   make demo   set up (venv + install) and run the main job on the bundled scene and bag
#   make test   set up and run the whole test suite
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-slow bench setup clean

setup: $(STAMP)

$(STAMP): requirements.txt setup.py package.xml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade --quiet pip
	@echo "thinshell: installing the dependencies into $(VENV) (first run only; about 1-3 min with a warm pip cache)"
	$(PY) -m pip install --progress-bar on -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m thinshell_ros.cli demo

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" tests

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow tests

bench: $(STAMP)
	$(PY) -m thinshell_ros.cli bench forming --json

clean:
	rm -rf $(VENV) build install log *.egg-info
