"""Chunks of detector rows for the compiled loops, running a loop over them in threads, and counting flags per pixel.

A compiled loop over pixels works a chunk of rows at a time, each chunk with its own accumulators (summed
afterwards), so no two threads write the same memory (:mod:`dfxcorr.kernels`). Every module with compiled loops
imports this one, which sets how LLVM vectorises them (:data:`MEMORY_CHECKS`) before any of them compiles.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import llvmlite.binding as llvm
import numba
import numpy as np
from numba import njit, prange

#: Pairs of arrays LLVM may compare at run time to prove that a loop's stores do not overlap its loads. numba cannot
#: tell the compiler that two arrays are distinct, so a loop over a tile's columns that updates ten accumulators
#: while reading nine sample and channel rows needs more pairs than LLVM's default (8, 128 under a pragma) and stayed
#: scalar ("too many memory checks needed"). The checks run once per loop, not per column; the vectorised loop
#: computes each column exactly as the scalar one (no reassociation), so results are unchanged.
MEMORY_CHECKS = 1000
llvm.set_option("dfxcorr", f"-runtime-memory-check-threshold={MEMORY_CHECKS}")
llvm.set_option("dfxcorr", f"-vectorize-memory-check-threshold={MEMORY_CHECKS}")


def row_chunks(starts: np.ndarray, n_blocks: int, *, per_thread: int = 4) -> np.ndarray:
    """Row boundaries of chunks holding about equal numbers of blocks.

    Parameters
    ----------
    starts : ndarray of int, shape (R,)
        First block of each row.
    n_blocks : int
        K.
    per_thread : int
        Chunks per thread (more chunks balance uneven rows, fewer keep the per-chunk accumulators small).

    Returns
    -------
    ndarray of int64, shape (m + 1,), m <= per_thread x threads
        Chunk i holds rows ``bounds[i]:bounds[i + 1]``.
    """
    n = max(1, min(starts.size, per_thread * numba.get_num_threads()))
    return row_bounds(starts, np.linspace(0, n_blocks, n + 1)[1:-1])


def row_bounds(starts: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Row boundaries that cut the rows at the first row starting at or after each of the block positions ``blocks``
    (whole rows, none empty): :func:`row_chunks`' and :meth:`Observations.row_ranges`'.

    Parameters
    ----------
    starts : ndarray of int, shape (R,)
        First block of each row.
    blocks : ndarray, shape (n,)
        Block positions to cut at, ascending.

    Returns
    -------
    ndarray of int64, shape (m + 1,), m <= n + 1
        Chunk i holds rows ``bounds[i]:bounds[i + 1]``, from 0 to R.
    """
    cuts = np.searchsorted(starts, blocks, side="left")
    return np.unique(np.concatenate([[0], cuts, [starts.size]])).astype(np.int64)


def over_chunks(rows, chunks: np.ndarray, before: tuple, after: tuple, outs: tuple) -> None:
    """Run a compiled loop over chunks of rows on numba's thread count (:func:`set_threads`).

    Calls ``rows(*before, chunks[t], chunks[t + 1], *after, *(o[t] for o in outs))`` for every chunk t, in threads of
    this process: ``rows`` releases the GIL and writes only to its chunk's outputs ``o[t]``. Not numba's parallel loop:
    that compiles the function it calls a second time, into the loop (4-9 s per kernel at a first run).

    Parameters
    ----------
    rows : callable
        A numba dispatcher compiled with ``nogil=True``, or a function whose work releases the GIL (numpy's
        elementwise functions on large arrays).
    chunks : ndarray of int64, shape (n + 1,)
        Row boundaries (:func:`row_chunks`).
    before, after : tuple
        Arguments before and after the chunk's first and last row.
    outs : tuple of ndarray
        Per-chunk outputs, each of first dimension n.
    """
    n = chunks.size - 1

    def one(t: int) -> None:
        rows(*before, chunks[t], chunks[t + 1], *after, *(o[t] for o in outs))

    threads = min(numba.get_num_threads(), n)
    if threads <= 1:
        for t in range(n):
            one(t)
        return
    list(_pool(threads).map(one, range(n)))


#: The process's thread pools, one per thread count: a pool started for each call took 0.6 ms against 0.17 ms for one
#: kept (a stepping scan's diagnosis makes about 600 calls). The tasks never wait on one another, so callers in several
#: threads may share a pool; a forked child starts without them (their threads are not in it).
_POOLS: dict[int, ThreadPoolExecutor] = {}
os.register_at_fork(after_in_child=_POOLS.clear)


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="dfxcorr")
    return _POOLS[threads]


@njit(cache=True, parallel=True)
def _row_counts(flags, bounds):
    R, C = bounds.size - 1, flags.shape[1]
    out = np.empty((R, C), np.int64)
    for r in prange(R):
        o = out[r]
        o[:] = 0
        for k in range(bounds[r], bounds[r + 1]):
            f = flags[k]
            for c in range(C):
                o[c] += f[c]
    return out


def row_counts(obs, flags: np.ndarray) -> np.ndarray:
    """How many of each pixel's samples are flagged: ``flags`` (K, C) bool -> (R, C) int64, what
    ``obs.segment_sum(flags.astype(float))`` gives, compiled (numpy's reduceat of a float copy took 15 ms per block of
    a full-resolution clinical scan, 2 s of its retrieval)."""
    return _row_counts(np.ascontiguousarray(flags, np.bool_), np.append(obs.starts, obs.frame.size).astype(np.int64))
