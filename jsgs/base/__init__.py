"""The bottom layer: what every other part of jsgs, and jsgstools, builds on, importing nothing of the project
but this package.

- :mod:`jsgs.base.errors` (the one-line errors), :mod:`jsgs.base.commands` (what every command line shares);
- :mod:`jsgs.base.io` (safe reading and writing), :mod:`jsgs.base.limits` (the bounds of what is read);
- the files: :mod:`jsgs.base.images`, :mod:`jsgs.base.manifest` (its cameras: :mod:`jsgs.base.camera`),
  :mod:`jsgs.base.ply`, :mod:`jsgs.base.run_files`;
- :mod:`jsgs.base.schema` (loading the JSON Schemas that the data package :mod:`jsgs.schemas` ships, and
  validating against them);
- small numerics: :mod:`jsgs.base.precision`, :mod:`jsgs.base.rotations`, :mod:`jsgs.base.known_grad`,
  :mod:`jsgs.base.kept_zeros`.
"""
