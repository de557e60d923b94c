"""The one decorator robotd's numba kernels are compiled with: :func:`jit`.

``jit`` is ``numba.njit(cache=True, nogil=True)`` plus, per kernel, the options the SLAM kernels
need (``fastmath``, ``inline``, ``parallel``). Every kernel module uses it (``frontend/_surf_kernels``,
``frontend/_detect_kernels``, ``frontend/_stereo_kernels``, ``_outlier_kernels``, ``slam/_kernels``),
so that all of them cache alike and all survive a read-only install.

Caching: ``cache=True`` writes compiled code next to the kernel's source file (``__pycache__``), or
where ``NUMBA_CACHE_DIR`` points. When neither that nor numba's per-user cache directory is
writable (a read-only install under a hardened service), numba refuses ``cache=True`` when the
function is decorated; :func:`jit` then compiles without a disk cache (every process pays the
compile once) and logs a warning. For the daemon set ``NUMBA_CACHE_DIR`` to a writable directory
(systemd: ``CacheDirectory=robotd`` and ``Environment=NUMBA_CACHE_DIR=/var/cache/robotd/numba``).
numba keys a cache entry by the kernel's source file and line, so moving or editing a kernel
recompiles it once.

``nogil=True``: a kernel called from Python releases the GIL while it runs, so the left and right
images can be processed in two threads, and the camera and detection threads run meanwhile.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Set
from typing import Any, Literal

import numba

logger = logging.getLogger(__name__)


def jit(
    fn: Callable[..., Any] | None = None,
    *,
    fastmath: bool | Set[str] = False,
    inline: Literal["never", "always"] = "never",
    parallel: bool = False,
) -> Any:
    """``numba.njit(cache=True, nogil=True, ...)``, falling back to no disk cache when none is writable.

    Use as ``@jit`` or ``@jit(fastmath=..., inline="always", parallel=True)``. ``fastmath``: False,
    True or a set of LLVM fast-math flags; ``inline``: ``"always"`` inlines the function into its
    numba callers at IR level; ``parallel``: enables ``numba.prange``. Options left at these
    defaults (numba's own) are not passed on, so ``@jit`` is exactly ``njit(cache=True, nogil=True)``.
    """
    options: dict[str, Any] = {}
    if fastmath:
        options["fastmath"] = fastmath
    if inline != "never":
        options["inline"] = inline
    if parallel:
        options["parallel"] = True

    def decorate(f: Callable[..., Any]) -> Any:
        try:
            return numba.njit(cache=True, nogil=True, **options)(f)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            logger.warning("numba disk cache unavailable for %s (%s); compiling per process", f.__name__, exc)
            return numba.njit(cache=False, nogil=True, **options)(f)

    return decorate if fn is None else decorate(fn)
