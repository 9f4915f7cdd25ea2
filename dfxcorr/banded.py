"""Symmetric block-tridiagonal systems, many at once: the images' normal equations where samples read between rows.

Where the beam paths move during the scan (``beam_path``) a sample's expected count mixes the images of two
neighbouring rows, so the images of a column are no longer one small solve per pixel: their normal matrix is
block tridiagonal along the rows (p x p blocks, p unknowns per pixel). These are its direct solve (block
Gaussian elimination, exact) and the blocks of its inverse that the leverages and the Fisher information need,
vectorised over the columns, the assembly of those normal matrices from the samples
(:class:`dfxcorr.observations.Reading`), and the profiled images' share of the Fisher information from them
(:func:`profiled_correction`; block diagonal where each sample reads its own row).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from .kernels import SINGULAR
from .observations import Observations


def forward(D: np.ndarray, U: np.ndarray, *, tol: float = SINGULAR) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverses of the forward Schur complements F_q = D_q - U_{q-1}^T F_{q-1}^-1 U_{q-1}.

    A row whose complement is near singular (|det F_q| <= ``tol``, the diagonal scaled to 1: what its samples tell
    of some combination of its unknowns is already in the rows before it, e.g. two rows read only by the samples
    between them at one fraction) is held apart, as a pixel or a row whose own block is near singular: its F is the
    identity and its couplings are zero, so that it decouples from its neighbours (they are solved with it fixed at 0;
    :meth:`ReadBetween.solve` sets it to 0) rather than taking the huge values of a near-singular elimination. Where
    only some of its unknowns are undetermined the others are held too, at 0.

    Parameters
    ----------
    D : ndarray, shape (R, C, p, p)
        Diagonal blocks (symmetric positive definite, scaled to a unit diagonal), C independent systems.
    U : ndarray, shape (R, C, p, p)
        U[q] is the block coupling row q with row q + 1 (U[R - 1] is not read).
    tol : float
        |det F_q| at or below which row q is held apart.

    Returns
    -------
    Finv : ndarray, shape (R, C, p, p)
    U : ndarray, shape (R, C, p, p)
        The couplings, zero at the rows held apart.
    held : ndarray of bool, shape (R, C)
        The rows held apart.
    """
    U = U.copy()
    Finv = np.empty_like(D)
    held = np.zeros(D.shape[:2], bool)
    eye = np.eye(D.shape[-1])
    for q in range(D.shape[0]):
        F = D[q] - np.swapaxes(U[q - 1], -1, -2) @ Finv[q - 1] @ U[q - 1] if q else D[q]
        held[q] = np.abs(np.linalg.det(F)) <= tol
        F = np.where(held[q][:, None, None], eye, F)
        if q:
            U[q - 1][held[q]] = 0.0
        U[q][held[q]] = 0.0
        Finv[q] = np.linalg.inv(F)
    return Finv, U, held


def solve(Finv: np.ndarray, U: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the block-tridiagonal systems given their :func:`forward` factors.

    Parameters
    ----------
    Finv, U : ndarray, shape (R, C, p, p)
    rhs : ndarray, shape (R, C, p, m)
        m right-hand sides per system.

    Returns
    -------
    x : ndarray, shape (R, C, p, m)
    """
    R = rhs.shape[0]
    y = np.empty_like(rhs)
    y[0] = rhs[0]
    for q in range(1, R):
        y[q] = rhs[q] - np.swapaxes(U[q - 1], -1, -2) @ (Finv[q - 1] @ y[q - 1])
    x = np.empty_like(rhs)
    x[R - 1] = Finv[R - 1] @ y[R - 1]
    for q in range(R - 2, -1, -1):
        x[q] = Finv[q] @ (y[q] - U[q] @ x[q + 1])
    return x


def inverse_blocks(Finv: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal blocks of the inverse and those coupling each row with the next.

    Sigma_{R-1} = F_{R-1}^-1; Sigma_{q,q+1} = -F_q^-1 U_q Sigma_{q+1}; Sigma_q = F_q^-1 - Sigma_{q,q+1} U_q^T F_q^-1.

    Returns
    -------
    diagonal : ndarray, shape (R, C, p, p)
    upper : ndarray, shape (R, C, p, p)
        upper[q] = Sigma_{q,q+1} (zero for the last row).
    """
    R = Finv.shape[0]
    diag = np.empty_like(Finv)
    upper = np.zeros_like(Finv)
    diag[R - 1] = Finv[R - 1]
    for q in range(R - 2, -1, -1):
        upper[q] = -Finv[q] @ U[q] @ diag[q + 1]
        diag[q] = Finv[q] - upper[q] @ np.swapaxes(U[q], -1, -2) @ Finv[q]
    return diag, upper


@dataclass
class ReadBetween:
    """The images' normal matrices of every column where the samples read between rows, factored.

    Scaled by the square roots of their diagonals (``scale``), rows that cannot be solved set to the identity;
    ``Finv`` and ``U`` are the scaled system's :func:`forward` factors.

    Attributes
    ----------
    scale : ndarray, shape (R, C, p)
    valid : ndarray of bool, shape (R, C)
    Finv, U : ndarray, shape (R, C, p, p)
    """

    scale: np.ndarray
    valid: np.ndarray
    Finv: np.ndarray
    U: np.ndarray

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """N^-1 rhs for right-hand sides (R, C, p, m); 0 on rows that cannot be solved."""
        s = self.scale[..., None]
        x = solve(self.Finv, self.U, np.where(self.valid[..., None, None], rhs / s, 0.0)) / s
        x[~self.valid] = 0.0
        return x

    def inverse(self) -> tuple[np.ndarray, np.ndarray]:
        """The inverse's diagonal blocks and those between each row and the next (zero on unsolvable rows)."""
        diag, upper = inverse_blocks(self.Finv, self.U)
        s = self.scale
        diag = diag / (s[..., :, None] * s[..., None, :])
        upper[:-1] = upper[:-1] / (s[:-1, ..., :, None] * s[1:, ..., None, :])
        diag[~self.valid] = 0.0
        return diag, upper


def _read_shares(obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each block's two image rows (positions in ``obs.rows``) and the share of the first (its own row, whole,
    without a reading)."""
    lo, hi, frac = obs.read_rows()
    return lo, hi, 1.0 - frac


def _spread(index: np.ndarray, share: np.ndarray, rows: int) -> sparse.csr_matrix:
    """The (rows, K) matrix that adds each block's ``share`` of a per-sample value to image row ``index``."""
    return sparse.csr_matrix((share, (index, np.arange(index.size))), shape=(rows, index.size))


def factor_read_between(obs: Observations, columns: list[np.ndarray], weights: np.ndarray) -> ReadBetween:
    """Assemble and factor the images' normal matrices where the samples read between rows (``obs.reading``).

    Sample k's model is sum_a X_a ((1 - f_k) coef[lo_k, a] + f_k coef[lo_k + 1, a]), so the normal matrix of a
    column is block tridiagonal along the rows. Unknowns absent from every sample of a row (no fringe) are left
    out there, as in the per-pixel solve; a row is solvable with at least p samples reading it, the first column
    present, a well-conditioned diagonal block and a well-conditioned complement in the elimination (:func:`forward`).
    """
    lo, hi, g = _read_shares(obs)
    R, p = obs.rows.size, len(columns)
    own, nxt, both = _spread(lo, g ** 2, R), _spread(hi, (1 - g) ** 2, R), _spread(lo, g * (1 - g), R)
    wX = [weights * X for X in columns]
    D = np.empty((R, weights.shape[1], p, p))
    U = np.zeros_like(D)
    for a in range(p):
        for b in range(a, p):
            prod = wX[a] * columns[b]
            D[..., a, b] = D[..., b, a] = own @ prod + nxt @ prod
            U[..., a, b] = U[..., b, a] = both @ prod
    counted = (weights > 0).astype(np.float64)
    n_used = _spread(lo, (g > 0) * 1.0, R) @ counted + _spread(hi, (g < 1) * 1.0, R) @ counted
    diag = np.einsum("...ii->...i", D)
    present = diag > 0
    scale = np.sqrt(np.where(present, diag, 1.0))
    Ds = np.where(present[..., :, None] | present[..., None, :], D / (scale[..., :, None] * scale[..., None, :]), 0.0)
    Ds += np.eye(p) * ~present[..., None, :]
    Us = np.zeros_like(U)
    Us[:-1] = U[:-1] / (scale[:-1, ..., :, None] * scale[1:, ..., None, :])
    valid = (n_used >= present.sum(axis=-1)) & present[..., 0] & (np.abs(np.linalg.det(Ds)) > SINGULAR)
    # a row that cannot be solved is held at 0, apart from its neighbours (their elimination stays finite)
    Ds[~valid] = np.eye(p)
    Us[~valid] = 0.0
    Us[:-1][~valid[1:]] = 0.0
    Finv, Us, held = forward(Ds, Us)
    return ReadBetween(scale, valid & ~held, Finv, Us)


def read_between_rhs(obs: Observations, values: list[np.ndarray]) -> np.ndarray:
    """Per-sample values (p of them, each (K, C, ...)) summed onto the image rows the samples read, with their shares:
    X^T applied to them, shape (R, C, p, ...)."""
    lo, hi, g = _read_shares(obs)
    R = obs.rows.size
    first, second = _spread(lo, g, R), _spread(hi, 1 - g, R)
    out = [(first @ v.reshape(v.shape[0], -1) + second @ v.reshape(v.shape[0], -1)).reshape((R,) + v.shape[1:])
           for v in values]
    return np.stack(out, axis=2)


def solve_read_between(obs: Observations, columns: list[np.ndarray], target: np.ndarray, weights: np.ndarray, *,
                       keep_inverse: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`dfxcorr.model.solve_pixels` where the samples read the images between rows (``obs.reading``): an exact
    solve of each column's block-tridiagonal normal equations (:func:`factor_read_between`).

    Returns
    -------
    coef : ndarray, shape (R, C, p)
    valid : ndarray of bool, shape (R, C)
    inverse, coupling : ndarray, shape (R, C, p, p), or None
        Diagonal blocks of the inverse normal matrix, and those between each row and the next (with
        ``keep_inverse``).
    """
    fac = factor_read_between(obs, columns, weights)
    coef = fac.solve(read_between_rhs(obs, [weights * X * target for X in columns])[..., None])[..., 0]
    if not keep_inverse:
        return coef, fac.valid, None, None
    inverse, coupling = fac.inverse()
    return coef, fac.valid, inverse, coupling


#: Columns whose normal equations :func:`profiled_correction` factors at once (its temporaries grow with them).
CORRECTION_COLUMNS = 16


def profiled_correction(obs: Observations, columns: list[np.ndarray], weights: np.ndarray, F: list[np.ndarray],
                        where: list[np.ndarray], n_params: int) -> np.ndarray:
    """The profiled images' share of the Fisher information, from the model's arrays.

    sum over columns of Y^T N^-1 Y, Y = X^T W F. Where the samples read between rows a pixel's images share samples
    with its neighbours', so N is the column's block-tridiagonal normal matrix (:func:`factor_read_between`; block
    diagonal where each sample reads its own row), solved :data:`CORRECTION_COLUMNS` columns at a time. The compiled
    :func:`dfxcorr.fisher_pixels.fisher` computes the same where every sample reads its own row and every component is a
    power of x.

    Parameters
    ----------
    obs : Observations
    columns : list of p ndarray, each (K, C)
        The images' design columns X_a at every sample (:func:`dfxcorr.model.image_columns`).
    weights : ndarray, shape (K, C)
    F : list of ndarray, each (K, C)
        dIbar/d(component) of each parameter component at every sample.
    where : list of ndarray of int, each (K,)
        The parameter (axis of the information) that component q of block k belongs to: its frame's for per-frame
        components, one index for a global one.
    n_params : int
        P.

    Returns
    -------
    ndarray, shape (P, P)
    """
    R, K = obs.rows.size, obs.frame.size
    lo, hi, g = _read_shares(obs)
    owners = [np.unique(wq, return_inverse=True) for wq in where]
    corr = np.zeros((n_params, n_params))
    for start in range(0, obs.columns.size, CORRECTION_COLUMNS):
        cols = np.arange(start, min(start + CORRECTION_COLUMNS, obs.columns.size))
        sub = obs.subset(cols, copy=False)
        Xs, w = [x[:, cols] for x in columns], weights[:, cols]
        fac = factor_read_between(sub, Xs, w)
        # Y of each column: (image row, column, unknown, parameter)
        Y = np.zeros((R, cols.size, len(columns), n_params))
        for (params, owner), Fq in zip(owners, F, strict=True):
            # sums over the samples of each (image row, parameter) pair, with what each sample reads of the row
            spread = sum(sparse.csr_matrix((share, (rows * params.size + owner, np.arange(K))),
                                           shape=(R * params.size, K))
                         for rows, share in ((lo, g), (hi, 1 - g)))
            for a, Xa in enumerate(Xs):
                Y[:, :, a, params] += np.moveaxis((spread @ (w * Xa * Fq[:, cols])).reshape(R, params.size, cols.size),
                                                  1, 2)
        corr += np.einsum("rcap,rcaq->pq", Y, fac.solve(Y), optimize=True)
    return corr
