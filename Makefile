# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
# Where torch comes from: pip's own index (this project's machines list the CPU wheel there). On
# a machine whose pip reaches plain PyPI, `make TORCH_INDEX=https://download.pytorch.org/whl/cpu`
# keeps the CPU build (PyPI's Linux wheel pulls the CUDA libraries).
TORCH_INDEX ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test test-all lint format typecheck bench lock clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# pip byte-compiles on one core; compileall does it on every core (as pip, ignoring files that
# are not Python 3.11, such as torch's own Python 3.12 test helper), except 8,000 of the 16,300
# modules: sympy, networkx and pip, which nothing here imports, PyOpenGL, imported only by the
# cheetah's video rendering, and Ray, imported only by the Ray job backend (a process importing
# them compiles the few modules it loads).
$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/pip install --quiet --no-compile $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) torch==2.13.0
	$(BIN)/pip install --quiet --no-compile -c constraints.txt -e '.[dev,ray]'
	$(BIN)/python -c "import compileall, re; compileall.compile_dir('$(VENV)/lib', quiet=2, \
		workers=0, rx=re.compile(r'/site-packages/(sympy|networkx|pip|OpenGL|ray)/'))"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m server.cli.demo

test: lint
	$(BIN)/pytest -q -n 3 --dist loadfile --no-loadscope-reorder

test-all: $(STAMP)
	$(BIN)/pytest -q -m ''

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/hadolint Dockerfile

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

typecheck: $(STAMP)
	$(BIN)/mypy

bench: $(STAMP)
	for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# constraints.txt: the versions installed now (after upgrading some by hand, say), as a new lock.
lock: $(STAMP)
	{ head -n 3 constraints.txt; $(BIN)/pip freeze --exclude-editable | grep -v '^torch=='; } \
		> constraints.txt.new && mv constraints.txt.new constraints.txt

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache .ruff_cache
