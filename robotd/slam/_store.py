"""Copy-on-write landmark storage for FastSLAM's particles (docs/architecture.md "Performance shape", docs/math.md §10).

Landmark slots are grouped in blocks of ``B`` consecutive slots. Each particle holds a row of block
indices into a shared pool:

- ``pool_mean`` (n_pool, B, dm), ``pool_cov`` (n_pool, B, dm, dm): the Gaussians, world frame
- ``table``     (P, n_cols) int64: particle k's slots ``[c·B, (c+1)·B)`` live in pool block ``table[k, c]``

Resampling only gathers rows of ``table`` (P × n_cols integers instead of P × M Gaussians); a block
shared by several particles is copied the first time one of them writes to it. Because landmark
slots are allocated in creation order and a robot mostly re-observes landmarks created around the
same time, one frame's writes touch few blocks. A pool block always stores the same slot range, so
the particles sharing it are exactly the repeated entries of one column of ``table``.

Unused pool blocks are garbage-collected after each resampling (a block is in use when some
table entry points at it).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

# copy_blocks(pool_mean, pool_cov, src (n,), dst (n,)): pool blocks src -> dst
CopyBlocksFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]


class LandmarkStore:
    """Per-particle landmark Gaussians with block-level copy on write."""

    def __init__(self, n_particles: int, dm: int, block: int = 64) -> None:
        if block < 1:
            raise ValueError(f"landmark block size: expected >= 1, got {block}")
        self.P, self.dm, self.B = int(n_particles), int(dm), int(block)
        self.table = np.zeros((self.P, 0), np.int64)
        self.pool_mean = np.zeros((0, self.B, dm))
        self.pool_cov = np.zeros((0, self.B, dm, dm))
        self.in_use = np.zeros(0, bool)
        self.n_copied_blocks = 0  # blocks copied on write since creation (diagnostics)

    # -------------------------------------------------------------------------------- capacity

    @property
    def capacity(self) -> int:
        """Number of landmark slots addressable by every particle."""
        return self.table.shape[1] * self.B

    @property
    def n_pool(self) -> int:
        return int(self.pool_mean.shape[0])

    def nbytes(self) -> int:
        """Bytes held by the pool and the table."""
        return int(self.pool_mean.nbytes + self.pool_cov.nbytes + self.table.nbytes)

    def _alloc_blocks(self, n: int) -> np.ndarray:
        """Indices of ``n`` free pool blocks (growing the pool geometrically)."""
        free = np.flatnonzero(~self.in_use)
        if free.size < n:
            old = self.n_pool
            new = max(2 * old, old + n - free.size, 16)
            pm = np.empty((new, self.B, self.dm))
            pc = np.empty((new, self.B, self.dm, self.dm))
            pm[:old] = self.pool_mean
            pc[:old] = self.pool_cov
            self.pool_mean, self.pool_cov = pm, pc
            self.in_use = np.concatenate([self.in_use, np.zeros(new - old, bool)])
            free = np.flatnonzero(~self.in_use)
        out = free[:n]
        self.in_use[out] = True
        return out

    def ensure_capacity(self, n_slots: int) -> None:
        """Make slots ``0 … n_slots-1`` addressable. New columns start as one block shared by all particles."""
        cols = -(-n_slots // self.B)
        have = self.table.shape[1]
        if cols <= have:
            return
        add = max(cols - have, have)  # grow by doubling to amortise the table copy
        blocks = self._alloc_blocks(add)
        self.pool_mean[blocks] = 0.0
        self.pool_cov[blocks] = 0.0
        self.table = np.concatenate([self.table, np.broadcast_to(blocks, (self.P, add))], 1)

    # ---------------------------------------------------------------------------- read / write

    def gather(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the Gaussians of ``slots`` (N,) in every particle: mean (P, N, dm), cov (P, N, dm, dm)."""
        b = self.table[:, slots // self.B]
        o = slots % self.B
        return self.pool_mean[b, o], self.pool_cov[b, o]

    def gather_particle(self, k: int, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Particle k's Gaussians of ``slots``: mean (N, dm), cov (N, dm, dm)."""
        b = self.table[k, slots // self.B]
        o = slots % self.B
        return self.pool_mean[b, o], self.pool_cov[b, o]

    def particle_means(self, k: int, slots: np.ndarray) -> np.ndarray:
        """Particle k's landmark means of ``slots``: (N, dm) copy, world frame."""
        return self.pool_mean[self.table[k, slots // self.B], slots % self.B]

    def make_writable(self, slots: np.ndarray, copy_blocks: CopyBlocksFn | None = None) -> None:
        """Copy on write: give every particle its own pool block for the columns of ``slots``.

        ``copy_blocks(pool_mean, pool_cov, src, dst)`` copies pool blocks ``src`` to ``dst`` (the
        numba one avoids numpy's gather temporary); default: numpy fancy indexing.
        """
        cols = np.unique(slots // self.B)
        if cols.size == 0:
            return
        entries = self.table[:, cols]  # (P, C); pool blocks are column-specific, so values never collide
        flat = entries.ravel()
        _, first = np.unique(flat, return_index=True)
        dup = np.ones(flat.size, bool)
        dup[first] = False
        pos = np.flatnonzero(dup)
        if pos.size == 0:
            return
        new = self._alloc_blocks(pos.size)
        src = flat[pos]
        if copy_blocks is None:
            self.pool_mean[new] = self.pool_mean[src]
            self.pool_cov[new] = self.pool_cov[src]
        else:
            copy_blocks(self.pool_mean, self.pool_cov, src, new)
        flat = flat.copy()
        flat[pos] = new
        self.table[:, cols] = flat.reshape(entries.shape)
        self.n_copied_blocks += int(pos.size)

    def scatter(self, slots: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> None:
        """Write mean (P, N, dm), cov (P, N, dm, dm) to ``slots`` (N,) of every particle (copy on write)."""
        self.make_writable(slots)
        b = self.table[:, slots // self.B]
        o = slots % self.B
        self.pool_mean[b, o] = mean
        self.pool_cov[b, o] = cov

    # ------------------------------------------------------------------------------ resampling

    def select(self, idx: np.ndarray) -> None:
        """The particle set becomes ``particles[idx]`` (any length): a table gather, no Gaussian copied."""
        self.table = self.table[idx]
        self.P = int(idx.size)
        used = np.zeros(self.n_pool, bool)
        used[self.table.ravel()] = True
        self.in_use = used

    # ----------------------------------------------------------------------------- persistence

    def dense(self, n_slots: int) -> tuple[np.ndarray, np.ndarray]:
        """All particles' slots ``0 … n_slots-1`` as dense arrays (P, n, dm), (P, n, dm, dm)."""
        return self.gather(np.arange(n_slots))

    @classmethod
    def from_dense(cls, mean: np.ndarray, cov: np.ndarray, block: int) -> LandmarkStore:
        """A store holding mean (P, n, dm), cov (P, n, dm, dm) with no sharing."""
        P, n, dm = mean.shape
        st = cls(P, dm, block)
        st.ensure_capacity(max(n, 1))
        if n:
            st.scatter(np.arange(n), mean, cov)
        return st
