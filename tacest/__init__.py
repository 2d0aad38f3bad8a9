"""tacest: learn an unknown rigid convex object by touch.

Layering (one way, docs/architecture.md): ``geometry`` → ``dynamics`` → ``model``
(stage models, effects) → ``estimation`` (problem, solve, result) →
``information``/``planning``/``diagnosis`` → ``dims`` (the dimension registry); file
I/O in ``io``, simulators and sensors in ``sim``/``sensors`` at the edges; the click
CLI (``tacest.cli``, source folder ``cli/``) thin on top.
"""

__version__ = "0.1.0"
