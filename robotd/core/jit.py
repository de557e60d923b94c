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

Whether a start compiles: :class:`CompileWatch` hears numba's own ``numba:compile`` event, which
numba raises only after its disk cache had no entry for the kernel (this source, this numba, this
CPU), so a start that loads everything from the cache raises none. The daemon announces the
compile when the first one begins, and never on a warm start.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Set
from typing import Any, Literal

import numba
from numba.core import event as numba_event

logger = logging.getLogger("robotd.jit")  # its name before the layer packages: users filter by it

UNCACHED: list[str] = []  # kernels decorated without a disk cache (none writable): every process compiles them


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
            UNCACHED.append(f"{f.__module__}.{f.__qualname__}")
            return numba.njit(cache=False, nogil=True, **options)(f)

    return decorate if fn is None else decorate(fn)


class CompileWatch(numba_event.Listener):
    """While entered (``with``), counts the kernels numba compiles because its cache had none
    (loads from the cache are not compiles), and calls ``on_first`` as the first one begins.

    The listener is process-wide: a compile on another thread meanwhile counts too. numba calls it
    with its compiler lock held (compiles are serialised), so its counters need no lock of their own."""

    def __init__(self, on_first: Callable[[], None] | None = None) -> None:
        self.on_first = on_first
        self.compiled = 0  # kernels compiled (numba's outermost compile events)
        self._depth = 0  # nesting: compiling a kernel compiles the kernels it calls
        self._installed = False

    def on_start(self, event: Any) -> None:
        self._depth += 1
        if self._depth == 1:
            self.compiled += 1
            if self.compiled == 1 and self.on_first is not None:
                self.on_first()

    def on_end(self, event: Any) -> None:
        self._depth = max(0, self._depth - 1)

    def __enter__(self) -> CompileWatch:
        numba_event.register("numba:compile", self)
        self._installed = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._installed:
            numba_event.unregister("numba:compile", self)
            self._installed = False
