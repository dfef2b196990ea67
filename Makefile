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
	# Mitsuba's CPU (LLVM) backend needs a newer libLLVM than Debian 12's default; it finds libllvm19 itself.
	-command -v apt-get >/dev/null && apt-get install -y -q libllvm19 >/dev/null
	.venv/bin/pip install -q -e '.[bench]'
	$(PY) benchmarks/run_all.py

.PHONY: install reproduce test bench
