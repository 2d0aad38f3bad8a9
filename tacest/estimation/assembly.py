"""Global sparse matrices of an NLP from small per-sample blocks: the residual Jacobian
(:func:`scatter_matrix`) and the upper triangle of the Lagrangian Hessian
(:func:`assemble_hessian`), each one constant sparse map applied to the stacked
nonzeros of the mapped per-sample functions, so that building them is O(samples).
Used by the 2-D and 3-D problems (tacest.estimation.problem2d, problem3d), with
:class:`LazyHessians`, which builds each Hessian model only when a solve asks for it."""

from __future__ import annotations

import casadi as ca
import numpy as np


def scatter_matrix(blocks, n_rows, n_cols):
    """A global sparse (n_rows, n_cols) MX matrix from local sparse blocks.
    blocks: list of (M MX (m, n_y · B): B local blocks side by side, each with the
    sparsity ``sp`` (m, n_y); rows (B, m) and cols (B, n_y) int global indices).  Entries
    that land on one global place are summed (a block whose inputs repeat one variable,
    e.g. a 3-D stage window at a run's start: the chain rule); without such repeats the
    map is a permutation of the stacked nonzeros."""
    import scipy.sparse as sp_

    rows, cols, src, vecs = [], [], [], []
    base = 0
    for Mx, sp, r_idx, c_idx in blocks:
        B = r_idx.shape[0]
        lr, lc = (np.asarray(a, int) for a in sp.get_triplet())
        nnz = len(lr)
        if Mx.sparsity() != ca.repmat(sp, 1, B):
            raise AssertionError("internal: local Jacobian blocks do not have the expected sparsity")
        rows.append(r_idx[:, lr].reshape(-1))
        cols.append(c_idx[:, lc].reshape(-1))
        src.append(base + np.arange(B * nnz))
        base += B * nnz
        vecs.append(ca.vec(Mx.nz[:]))
    rows, cols, src = np.concatenate(rows), np.concatenate(cols), np.concatenate(src)
    P = sp_.csc_matrix((src + 1.0, (rows, cols)), shape=(n_rows, n_cols))
    if P.nnz == len(src):  # no repeats: a permutation
        P.sort_indices()
        order = (P.data - 1).astype(np.int64)
        return ca.MX(ca.Sparsity(n_rows, n_cols, P.indptr.tolist(), P.indices.tolist()),
                     ca.vertcat(*vecs)[order.tolist()])
    return _summed(rows, cols, src, ca.vertcat(*vecs), n_rows, n_cols)


def _summed(rows, cols, src, values, n_rows, n_cols):
    """The (n_rows, n_cols) MX matrix whose entry (i, j) is the sum of values[src] over
    the entries with rows == i and cols == j: one constant sparse matrix times the values."""
    import scipy.sparse as sp_

    pattern = sp_.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_rows, n_cols))
    pattern.sum_duplicates()
    pattern.sort_indices()
    lookup = sp_.csc_matrix((np.arange(pattern.nnz) + 1.0, pattern.indices, pattern.indptr), shape=(n_rows, n_cols))
    nz_of = np.asarray(lookup[rows, cols]).reshape(-1).astype(np.int64) - 1
    A = sp_.csc_matrix((np.ones(len(src)), (nz_of, src)), shape=(pattern.nnz, values.shape[0]))
    A_dm = ca.DM(ca.Sparsity(A.shape[0], A.shape[1], A.indptr.tolist(), A.indices.tolist()), A.data)
    return ca.MX(ca.Sparsity(n_rows, n_cols, pattern.indptr.tolist(), pattern.indices.tolist()),
                 ca.mtimes(A_dm, values))


def assemble_hessian(blocks, n):
    """Sum local sparse blocks into the upper triangle of the global (n, n) Hessian.

    blocks: list of (H MX (n_y, n_y · B) — B local blocks side by side, each with the
    sparsity ``sp`` —, sp (n_y, n_y) local Sparsity, idx (B, n_y) int global indices).
    A 1x1 dense ``sp`` with idx (B, 1) adds diagonal entries.  The scatter-add is one
    constant sparse matrix times the stacked nonzeros of the local blocks.
    """
    rows, cols, src, vecs = [], [], [], []
    base = 0
    for H, sp, idx in blocks:
        B = idx.shape[0]
        lr, lc = (np.asarray(a, int) for a in sp.get_triplet())
        nnz = len(lr)
        gi = idx[:, lr]  # (B, nnz)
        gj = idx[:, lc]
        pos = base + np.arange(B)[:, None] * nnz + np.arange(nnz)[None, :]
        keep = gi <= gj
        rows.append(gi[keep])
        cols.append(gj[keep])
        src.append(pos[keep])
        base += B * nnz
        if H.sparsity() != ca.repmat(sp, 1, B):
            raise AssertionError("internal: local Hessian blocks do not have the expected sparsity")
        vecs.append(ca.vec(H.nz[:]))
    rows, cols, src = np.concatenate(rows), np.concatenate(cols), np.concatenate(src)
    return _summed(rows, cols, src, ca.vertcat(*vecs), n, n)


class LazyHessians(dict):
    """{mode: Function}, each built on first access from {mode: () -> MX expression}."""

    def __init__(self, builders, name, ins):
        super().__init__()
        self._builders, self._name, self._ins = builders, name, ins

    def __missing__(self, mode):
        if mode not in self._builders:
            raise KeyError(mode)
        fun = ca.Function(self._name, self._ins, [self._builders[mode]()], ["x", "p", "lam_f", "lam_g"],
                          ["triu_hess_gamma_x_x"])
        self[mode] = fun
        return fun
