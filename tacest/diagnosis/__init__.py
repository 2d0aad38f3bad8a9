"""Sim-to-real diagnosis (``tacest diagnose``, docs/diagnosis.md).

Modules, in the order of the method::

    floor       residuals against the noise floor: degrees of freedom, windows, tests, shares
    heldout     pieces and folds of the held-out comparison
    transforms  the sensor-timing candidates as data transforms (latency, time_scale)
    candidates  one candidate per SPEC effect, parameter counts, screening signatures
    fitting     the fits: warm-started, with pinned parameters, through the estimator
    diagnose    diagnose(runs, ...) -> Diagnosis: where, which effect, how far; the verdict
    report      report.md and PNG figures
"""
