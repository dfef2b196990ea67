# Two commands do all set-up on a fresh machine (see README):
#   make reproduce   the main job
#   make test        the whole test suite
PY := .venv/bin/python
OUT ?= out

.venv/.installed: pyproject.toml
	python3 -m venv .venv
	.venv/bin/pip install -q --upgrade pip
	.venv/bin/pip install -q torch==2.13.0
	.venv/bin/pip install -q -e '.[test]'
	touch $@

install: .venv/.installed

reproduce: .venv/.installed
	$(PY) -m tiltfit reproduce -o $(OUT)/reproduce

test: .venv/.installed
	$(PY) -m pytest -n 2 --durations=15 tests

bench: .venv/.installed
	.venv/bin/pip install -q -e '.[bench]'
	$(PY) benchmarks/run_all.py

.PHONY: install reproduce test bench
