"""Simulated 3-D recordings: the MuJoCo world, 3-D pokes and objects.

Modules (nothing here imports MuJoCo until a world is built):

- ``tacest.sim3d.objects``: boxes, random convex polytopes, polytopes from files, faces,
  resting orientations;
- ``tacest.sim3d.pokes``: the 3-D poke parameterization (POKE3_NAMES) and fingertip paths;
- ``tacest.sim3d.world``: the MuJoCo world with compliant fingers and physical effects;
- ``tacest.sim3d.record``: initial_state, simulate_pokes, record_sim, state_from_run.

Options, the effects registry, the sensor model and run-file appending are shared with
the 2-D recorder (tacest.sim).  See docs/simulation.md ("3-D").
"""
