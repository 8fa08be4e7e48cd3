# make demo : surfaces of four frog organs (examples/frog_demo.py) into demo-output/
# make test : the test suite
# Both create .venv with python3 if it is missing and install volreg (editable) with its
# test extra; the install is redone only when pyproject.toml changes.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.volreg-installed

.PHONY: demo test

demo: $(STAMP)
	$(PY) examples/frog_demo.py demo-output

test: $(STAMP)
	$(PY) -m pytest -q

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(VENV)/bin/pip install -e '.[test]'
	touch $(STAMP)
