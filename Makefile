# make demo : the main job, `volreg demo`: pyvista's frog labels registered to a copy deformed
#             by a known warp, every output of `volreg register` into demo-output/
# make test : the test suite, every tier (unit, integration, system)
# make test-quick : all but the system tier (whole commands in fresh interpreters, cold
#             compilations, signals), for a check in a minute or two
# Both create .venv with python3 if it is missing and install volreg (editable) with its
# test extra; the install is redone only when pyproject.toml changes.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.volreg-installed

.PHONY: demo test test-quick

demo: $(STAMP)
	$(VENV)/bin/volreg demo -o demo-output --force

test: $(STAMP)
	$(PY) -m pytest -q

test-quick: $(STAMP)
	$(PY) -m pytest -q -m "not system"

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(VENV)/bin/pip install -e '.[test]'
	touch $(STAMP)
