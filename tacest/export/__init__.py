"""Use what was learned: the estimated object as a model other tools load.

- :mod:`tacest.export.model`: an estimate as a 3-D rigid body (ExportBody); 2-D
  estimates extruded to a stated depth;
- :mod:`tacest.export.formats`: MJCF, URDF, SDF, OBJ/STL/GLB and the pose CSV;
- :mod:`tacest.export.replay`: a recorded run's finger motion replayed in MuJoCo
  against an exported MJCF, and its distance from the estimated trajectory.

``tacest export`` (cli/export.py) is the command; docs/export.md the documentation.
"""
