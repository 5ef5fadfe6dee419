# Two commands set everything up on a fresh machine:
#   make demo   - create .venv, install hybridhdr[demo] (no PyTorch), run the main job on a built-in default
#   make test   - create .venv, install with test extras (CPU PyTorch), run the test suite
#   make test-fast - the same without the tests marked slow (the local loop; make test runs everything)
#   make tour   - the README's tour test on the demo install (.venv-demo: hybridhdr[demo] + pytest)
# Both install the exact versions of constraints/ci.txt (`make constraints` regenerates it).
# The simulate extra (in both) brings the karellen-llvm-core wheel, the libLLVM Mitsuba's fast llvm_ad_mono
# renderer loads without root; NO_LLVM_WHEEL=1 removes it after installing (to try the scalar_rgb fallback;
# after `make clean`).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
CONSTRAINTS ?= constraints/ci.txt
# torch and torchvision come together from the PyTorch CPU index (matched CPU builds); where it cannot
# be reached pip takes them from its other sources (a local wheel cache); TORCH_INDEX= skips it
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
PIPC := $(PIP) install --quiet -c $(CONSTRAINTS)

.PHONY: demo test test-fast tour venv install install-test bench clean constraints

$(VENV)/.created:
	$(PYTHON) -m venv $(VENV)
	$(PIPC) --upgrade pip
	touch $@

NO_LLVM_WHEEL ?=
NO_WHEEL_STEP = if [ -n "$(NO_LLVM_WHEEL)" ]; then $(PIP) uninstall --quiet -y karellen-llvm-core; fi
# karellen-llvm-core is a wheel-axle wheel: the first interpreter started after its install finishes
# the install from a startup (.pth) file, and that imports pip. In that one process setuptools then
# hands out the standard library's deprecated distutils (its shim steps aside once pip is imported),
# so a later `import setuptools` (torch.utils.cpp_extension, under pycvvdp) warns, and under the
# suite's filterwarnings=error the first pytest run after an install failed. Start an interpreter once
# right after installing, so that no run of ours is the finishing one.
FINISH_STEP = $(PY) -c "pass"

$(VENV)/.installed: $(VENV)/.created pyproject.toml $(CONSTRAINTS)
	$(PIPC) -e ".[demo]"
	$(NO_WHEEL_STEP)
	$(FINISH_STEP)
	touch $@

$(VENV)/.torch: $(VENV)/.created $(CONSTRAINTS)
	@idx="$(TORCH_INDEX)"; \
	if [ -n "$$idx" ] && ! $(PY) tools/reachable.py "$$idx/torch/"; then \
	    echo "$$idx cannot be reached: torch and torchvision from pip's other sources (versions as constrained)"; idx=; fi; \
	echo $(PIPC) $${idx:+--extra-index-url $$idx} torch torchvision; \
	$(PIPC) $${idx:+--extra-index-url $$idx} torch torchvision
	touch $@

$(VENV)/.installed-test: $(VENV)/.torch pyproject.toml $(CONSTRAINTS)
	$(PIPC) -e ".[test,bench]"
	$(NO_WHEEL_STEP)
	$(FINISH_STEP)
	touch $@

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

demo: $(VENV)/.installed
	$(VENV)/bin/hybridhdr demo --out demo_out

test: $(VENV)/.installed-test
	$(PY) -m pytest -q

test-fast: $(VENV)/.installed-test
	$(PY) -m pytest -q -m "not slow"

# the README's tour on what `make demo` installs (hybridhdr[demo] and pytest, no test extras), in
# its own venv so that `make test`'s extras cannot hide a missing dependency
DEMO_VENV ?= .venv-demo
tour:
	$(MAKE) VENV=$(DEMO_VENV) install
	$(DEMO_VENV)/bin/pip install --quiet -c $(CONSTRAINTS) pytest
	$(DEMO_VENV)/bin/python -m pytest -q tests/test_readme_tour.py

bench: $(VENV)/.installed-test
	for b in benchmarks/*.py; do $(PY) $$b --quick || exit 1; done

# regenerate constraints/ci.txt from pyproject.toml's ranges (tools/update_constraints.py)
constraints:
	$(PYTHON) tools/update_constraints.py

clean:
	rm -rf $(VENV) $(DEMO_VENV) demo_out .pytest_cache .hypothesis *.egg-info
