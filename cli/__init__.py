"""The ``tacest`` command line (installed as the package ``tacest.cli``).

Thin on top: commands parse and validate options, then call the library.  Heavy
modules (casadi, pymunk, trimesh, cv2, mujoco) are imported inside the commands.
"""
