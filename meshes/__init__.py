"""Model builders of the demos, benchmarks and tests: gmsh geometries meshed for DOLFINx.

One module a model, imported by name with the repository on ``PYTHONPATH`` (``scripts/fenicsx``
puts it there), e.g. ``from meshes import leg``:

- :mod:`meshes.hertz`: a hemisphere resting on a block (Hertz contact), quarter or full;
- :mod:`meshes.leg`: a synthetic right leg around the knee (bones, tendons, muscles, skin);
- :mod:`meshes.rods`: rods standing on a slanted foundation (falling rods);
- :mod:`meshes.snake`: a snake and an apple in front of its mouth.

Each module also runs as a script (``python3 meshes/leg.py``) that meshes its model, prints its
size and writes it to XDMF.
"""
