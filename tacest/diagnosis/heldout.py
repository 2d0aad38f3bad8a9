"""Held-out data for comparing models: pieces of the recordings, and folds.

Pieces.  With several runs, every run is a piece.  With one run, the run is cut at its
action (poke) boundaries (tacest.io.slicing.action_ranges) and every poke is a
piece.  A fold holds out some pieces and trains on the others; with P pieces there are
K = min(P, max_folds) folds, fold j holding out pieces j, j + K, j + 2K, ... so that
every piece is held out exactly once.

Fit on the training pieces, then fit the held-out pieces with the trained parameters
held fixed (only trajectories, impulses and, with the local back end, the shape are
fitted there: see tacest.diagnosis.fitting) and sum their objective.
"""

from __future__ import annotations

from dataclasses import dataclass

from tacest.io.slicing import action_ranges, slice_run, slice_run_estimate

#: default largest number of folds (each fold costs one training and one held-out fit
#: per candidate)
MAX_FOLDS = 3


@dataclass(frozen=True)
class Piece:
    """Samples [start, stop) of input run ``run``."""

    run: int
    start: int
    stop: int

    def cut(self, runs: list):
        """This piece of ``runs[self.run]`` (the whole run when it spans it)."""
        r = runs[self.run]
        if self.start == 0 and self.stop == r.n_samples:
            return r
        return slice_run(r, self.start, self.stop)

    def cut_estimate(self, estimate):
        """This piece of an estimate's trajectory of the same runs (a RunEstimate)."""
        re = estimate.runs[self.run]
        if self.start == 0 and self.stop == len(re.pose):
            return re
        return slice_run_estimate(re, self.start, self.stop)


@dataclass(frozen=True)
class Fold:
    """Training and held-out pieces of one fold."""

    index: int
    train: tuple
    heldout: tuple


def make_pieces(runs: list) -> list:
    """Pieces of the runs (see module doc); fewer than 2 means no held-out comparison."""
    if len(runs) >= 2:
        return [Piece(i, 0, r.n_samples) for i, r in enumerate(runs)]
    return [Piece(0, a, b) for a, b in action_ranges(runs[0])]


def make_folds(pieces: list, max_folds: int = MAX_FOLDS) -> list:
    """Folds over the pieces (see module doc); [] for fewer than 2 pieces."""
    P = len(pieces)
    if P < 2:
        return []
    K = max(2, min(P, int(max_folds)))
    return [Fold(index=j, train=tuple(p for i, p in enumerate(pieces) if i % K != j),
                 heldout=tuple(p for i, p in enumerate(pieces) if i % K == j)) for j in range(K)]


def describe_pieces(pieces: list, runs: list) -> str:
    """One line: how the data were cut."""
    if len(runs) >= 2:
        return f"{len(pieces)} runs, each held out once"
    return f"1 run cut at its action boundaries into {len(pieces)} pieces, each held out once"
