"""Simulated recordings: the 2-D pymunk world, pokes, and injectable effects.

Modules (import what you need; nothing here imports pymunk until a world is built):

- ``tacest.sim.effects``: the registry of unmodelled effects (SPEC names), parsing and
  JSON forms; no pymunk, reusable by the diagnosis;
- ``tacest.sim.objects``: boxes, random convex polygons, polygons from files, resting poses;
- ``tacest.sim.pokes``: the poke parameterization (POKE_NAMES) and fingertip paths;
- ``tacest.sim.world``: the pymunk world with compliant fingers and physical effects;
- ``tacest.sim.record``: SimOptions, record_sim, simulate_pokes, state_from_run, the
  sensor model.

See docs/simulation.md and docs/effects.md.
"""
