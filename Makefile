# Two commands set everything up on a fresh machine:
#   make demo   - create .venv, install hybridhdr[demo] (no PyTorch), run the main job on a built-in default
#   make test   - create .venv, install with test extras (CPU PyTorch), run the test suite
#   make test-fast - the same without the tests marked slow (the local loop; make test runs everything)
# Both install the exact versions of constraints/ci.txt (`make constraints` regenerates it).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
CONSTRAINTS ?= constraints/ci.txt
# torch and torchvision come together from the PyTorch CPU index (matched CPU builds); where it cannot
# be reached pip takes them from its other sources (a local wheel cache); TORCH_INDEX= skips it
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
PIPC := $(PIP) install --quiet -c $(CONSTRAINTS)

.PHONY: demo test test-fast venv install install-test bench clean constraints

$(VENV)/.created:
	$(PYTHON) -m venv $(VENV)
	$(PIPC) --upgrade pip
	touch $@

$(VENV)/.installed: $(VENV)/.created pyproject.toml $(CONSTRAINTS)
	$(PIPC) -e ".[demo]"
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
	touch $@

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

demo: $(VENV)/.installed
	$(VENV)/bin/hybridhdr demo --out demo_out

test: $(VENV)/.installed-test
	$(PY) -m pytest -q

test-fast: $(VENV)/.installed-test
	$(PY) -m pytest -q -m "not slow"

bench: $(VENV)/.installed-test
	for b in benchmarks/*.py; do $(PY) $$b --quick || exit 1; done

# regenerate constraints/ci.txt from pyproject.toml's ranges (tools/update_constraints.py)
constraints:
	$(PYTHON) tools/update_constraints.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache .hypothesis *.egg-info
