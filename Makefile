# make demo : the main job, `volreg demo`: pyvista's frog labels registered to a copy deformed
#             by a known warp, every output of `volreg register` into demo-output/
# make test : the test suite
# Both create .venv with python3 if it is missing and install volreg (editable) with its
# test extra; the install is redone only when pyproject.toml changes.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.volreg-installed

.PHONY: demo test

demo: $(STAMP)
	$(VENV)/bin/volreg demo -o demo-output --force

test: $(STAMP)
	$(PY) -m pytest -q

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(VENV)/bin/pip install -e '.[test]'
	touch $(STAMP)
