"""User-facing errors.

Every error a user can cause (bad file, bad option, infeasible start, failed solve)
is raised as a :class:`TacestError`.  The CLI turns it into one line on stderr and
exit status 2; library users can catch it.
"""


class TacestError(Exception):
    """An error caused by the input or by a solve that did not succeed.

    The message is one line, fit to show a user as is.
    """


class FileFormatError(TacestError):
    """A file breaks the SPEC: names the file and the offending HDF5 path."""

    def __init__(self, filename, h5path, problem):
        self.filename = str(filename)
        self.h5path = h5path
        self.problem = problem
        where = f"{self.filename}: {h5path}: " if h5path else f"{self.filename}: "
        super().__init__(where + problem)


class SolveFailedError(TacestError):
    """IPOPT (or another solver) did not return an acceptable solution."""
