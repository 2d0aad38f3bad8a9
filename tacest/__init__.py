"""tacest: learn an unknown rigid convex object by touch.

Layering (one way, docs/architecture.md): ``geometry`` → ``dynamics`` → ``model``
(stage models, effects) → ``estimation`` (problem, solve, result) →
``information``/``planning``/``diagnosis`` → ``dims`` (the dimension registry); file
I/O in ``io``, simulators and sensors in ``sim``/``sensors`` at the edges; the click
CLI (``tacest.cli``, source folder ``cli/``) thin on top.
"""

import os as _os

__version__ = "0.1.0"

#: the BLAS of numpy and of CasADi's IPOPT/MUMPS (both OpenBLAS) on one thread per
#: process unless the user chose otherwise: their matrices are small, and OpenBLAS's
#: spinning threads took a third more wall time beside other work on 2 cores (a 2-D
#: estimate 40 s instead of 29 s); parallel work goes through tacest.parallel's
#: processes.  Read when each library loads, so set before numpy and casadi are imported.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
