"""tacest: learn an unknown rigid convex object by touch.

Layering (one way): ``geometry``/``dynamics`` (models) → ``estimation`` (problem,
solver, results) → ``information``/``planning``/``diagnosis``; file I/O in ``io``,
simulators and sensors in ``sim``/``sensors`` at the edges; the click CLI
(``tacest.cli``, source folder ``cli/``) thin on top.
"""

__version__ = "0.1.0"
