"""The physics model, per dimension: the per-sample residual functions and their data
layout (stage models), and the effects that augment them (one interface, one registry).

Layer: above geometry and dynamics, below estimation (which assembles a model over runs
into an NLP and solves it), information, planning and diagnosis (which use the model
directly: a forward prediction needs the stage functions, not a whole NLP).
See docs/architecture.md.
"""
