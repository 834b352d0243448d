# Every target runs inside the FEniCSx environment given by scripts/fenicsx, which builds a
# Debian root on first use when the host has no DOLFINx >= 0.9 (FENICSX_SUITE=sid for 0.11).
FENICSX ?= scripts/fenicsx
NP ?= 2
PYTEST ?= python3 -m pytest -p no:cacheprovider --color=no --timeout=1200 --durations=25
PYTEST_ARGS ?=

.PHONY: demo demo-bar demo-rods test test-serial test-mpi lint format bench env docs notebooks demo-snake demo-knee

demo:  ## the main job: the concave-corner comparison (paper section 5), pictures in demos/output/
	$(FENICSX) python3 demos/demo_concave_corner.py

demo-bar:  ## the hyperelastic bar (no contact), pictures in demos/output/
	$(FENICSX) python3 demos/demo_hyperelastic_bar.py

demo-rods:  ## falling rods (paper Fig. 24): implicit dynamics with contact, frames and GIF in demos/output/
	$(FENICSX) python3 demos/demo_falling_rods.py

demo-snake:  ## a snake swallows an apple (paper Fig. 23): frames, animation in demos/output/
	$(FENICSX) python3 demos/demo_snake_apple.py

demo-knee:  ## the paper's knee: a leg flexed 150 degrees in 50 steps (long), in demos/output/
	$(FENICSX) nice -n 10 python3 demos/demo_knee.py

test: test-serial test-mpi  ## serial suite, then the suite under mpirun -n $(NP)

test-serial:
	$(FENICSX) $(PYTEST) -q $(PYTEST_ARGS) tests

test-mpi:
	$(FENICSX) mpirun -n $(NP) $(PYTEST) -q $(PYTEST_ARGS) tests

lint:
	$(FENICSX) ruff check .
	$(FENICSX) ruff format --check .

format:
	$(FENICSX) ruff check --fix .
	$(FENICSX) ruff format .

bench:
	for b in benchmarks/bench_*.py; do $(FENICSX) python3 $$b || exit 1; done

env:  ## print the versions the environment provides
	$(FENICSX) python3 -c "import dolfinx, numba, petsc4py, sys; print('python', sys.version.split()[0], 'dolfinx', dolfinx.__version__, 'numba', numba.__version__, 'petsc4py', petsc4py.__version__)"

notebooks:  ## every demo as a notebook, executed headless (reduced size) into docs/demos/
	$(FENICSX) python3 docs/run_notebooks.py

docs: notebooks  ## the documentation site (warnings are errors) into docs/_build/html
	$(FENICSX) python3 -m sphinx -W --keep-going -n -q -b html docs docs/_build/html
