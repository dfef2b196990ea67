# Two commands do all set-up on a fresh machine (see README):
#   make reproduce   the main job
#   make test        the whole test suite
PY := .venv/bin/python
OUT ?= out

# Mitsuba's fast CPU variant (llvm_ad_rgb: Embree hits behind the renderer's default `intersector="auto"`) needs
# libLLVM >= 16; Debian 12 ships 14 and 15 by default and 19 as libllvm19. As root with apt-get it is installed;
# otherwise one line says what to install and what is lost without it.
LLVM_PROBE := from renderer.mitsuba.variants import jit_variant_runs as r; raise SystemExit(not r('llvm_ad_rgb'))
LLVM_LINE := renderer: Mitsuba's llvm variant does not run here (it needs libLLVM >= 16, e.g. apt-get install libllvm19): renders use the pure-torch tracer, about 5x slower; everything else works

.venv/.installed: pyproject.toml
	python3 -m venv .venv
	.venv/bin/pip install -q --upgrade pip
	.venv/bin/pip install -q torch==2.13.0
	.venv/bin/pip install -q -e '.[test]'
	@$(PY) -c "$(LLVM_PROBE)" || ! [ "$$(id -u)" = 0 ] || ! command -v apt-get >/dev/null || { \
	  echo "installing Debian's libllvm19 for Mitsuba's llvm variant"; \
	  apt-get install -y -q libllvm19 >/dev/null 2>&1 || { apt-get update -q >/dev/null 2>&1 && \
	  apt-get install -y -q libllvm19 >/dev/null 2>&1; } || true; }
	@$(PY) -c "$(LLVM_PROBE)" || echo "$(LLVM_LINE)"
	touch $@

install: .venv/.installed

reproduce: .venv/.installed
	$(PY) -m tiltfit reproduce -o $(OUT)/reproduce

# The mrcal cross-check (tests/tiltfit/test_mrcal.py) runs mrcal itself: Debian's python3-mrcal, for the system
# Python. As root with apt-get it is installed; otherwise that test is skipped.
MRCAL_PROBE := /usr/bin/python3 -c "import mrcal" >/dev/null 2>&1

test: .venv/.installed
	@$(MRCAL_PROBE) || ! [ "$$(id -u)" = 0 ] || ! command -v apt-get >/dev/null || { \
	  echo "installing Debian's python3-mrcal for the mrcal cross-check"; \
	  apt-get install -y -q python3-mrcal >/dev/null 2>&1 || { apt-get update -q >/dev/null 2>&1 && \
	  apt-get install -y -q python3-mrcal >/dev/null 2>&1; } || true; }
	@$(MRCAL_PROBE) || echo "tiltfit: mrcal (Debian's python3-mrcal) is not installed: its cross-check is skipped"
	$(PY) -m pytest -n 2 --durations=15 tests

bench: .venv/.installed
	.venv/bin/pip install -q -e '.[bench]'
	$(PY) benchmarks/run_all.py

.PHONY: install reproduce test bench
