# The two commands of the README. Each creates .venv and installs what it needs.
#   make demo   the main job: end-to-end demo on the built-in objects
#   make test   the test suite (what CI runs)
PYTHON ?= python3
VENV ?= .venv
# torch and the torchvision built for it (torchvision's detectors: popcode-train train-detector); both from the
# machine's local wheels where it has them.
TORCH ?= torch==2.14.1 torchvision==0.29.1
BIN := $(VENV)/bin
export PYOPENGL_PLATFORM ?= egl

$(BIN)/.installed: pyproject.toml runtime/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet $(TORCH)
	$(BIN)/python -m pip install --quiet -e "./runtime[depth,ros]" -e ".[dev,pathtrace]"
	# triton (a GPU compiler the CUDA build of torch brings) is never used on a CPU, and importing it beside Mesa's
	# EGL can crash the process at random (bench/results/detector-choices.md): gone, as in torch's CPU builds.
	$(BIN)/python -m pip uninstall --quiet --yes triton
	touch $@

.PHONY: install demo test lint
install: $(BIN)/.installed

demo: $(BIN)/.installed
	$(BIN)/popcode-train demo --out runs/demo

# One pytest-xdist worker per core of the 2-core machine the suite must finish on in 8 minutes (tests/conftest.py
# gives each one thread); a test module stays in one worker, so a module's fixtures (a demo run, a rendered split)
# are built once. The modules are handed out in the order tests/conftest.py gives them, those with a slow test
# first (--no-loadscope-reorder: pytest-xdist's own order, by number of tests, left the minutes-long few-test
# modules for last, where one worker ran them while the other had finished).
TEST_WORKERS ?= 2
test: $(BIN)/.installed
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder

lint: $(BIN)/.installed
	$(BIN)/ruff check runtime trainer tests bench experiments tools
