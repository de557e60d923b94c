"""Checks of saved state read back from a map file, before any of it reaches a filter.

A map file's checksum proves the bytes are the ones written, not that they make sense: a map
written by another version, edited by hand or forged can hold a missing key, a string where an
array belongs, an array of the wrong shape or dtype, NaN, or a value no filter could start from
(an id counter at 2**63-1, a variance of 1e300). The readers here raise PersistenceError naming
the key and what was expected; nothing is converted or repaired (docs/reliability.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from robotd.core.errors import PersistenceError

POSITION_LIMIT_M = 1e6  # no rover is 1000 km from where it started its map
ANGLE_LIMIT_RAD = 4 * np.pi  # the filters keep angles wrapped to [-π, π]
VARIANCE_LIMIT = 1e8  # m² (σ = 10 km) or rad²: beyond this a Gaussian carries no information
INT64_MAX = 2**63 - 1
# landmark ids and the next id of a saved map: int64 with room for 2**40 more ids (40 new landmarks
# per frame at 30 Hz for 29 years)
ID_LIMIT = INT64_MAX - 2**40
COUNTER_LIMIT = 2**31  # existence counters move by one per frame
T_NS_LIMIT = 2**62  # timestamps (int64 nanoseconds)


class StateTable:
    """Typed access to one table of a saved state; ``where`` names it in every error."""

    def __init__(self, data: Any, where: str) -> None:
        if not isinstance(data, Mapping):
            raise PersistenceError(f"{where}: expected a table, got {_kind(data)}")
        self.data = data
        self.where = where

    def name(self, key: str) -> str:
        return f"{self.where}.{key}"

    def _get(self, key: str) -> Any:
        if key not in self.data:
            raise PersistenceError(f"{self.name(key)}: missing")
        return self.data[key]

    def table(self, key: str) -> StateTable:
        return StateTable(self._get(key), self.name(key))

    def has(self, key: str) -> bool:
        return key in self.data

    def integer(self, key: str, lo: int, hi: int) -> int:
        v = self._get(key)
        if isinstance(v, bool) or not isinstance(v, int | np.integer):
            raise PersistenceError(f"{self.name(key)}: expected an integer, got {_kind(v)}")
        if not lo <= int(v) <= hi:
            raise PersistenceError(f"{self.name(key)}: expected an integer in [{lo}, {hi}], got {int(v)}")
        return int(v)

    def number(self, key: str, lo: float, hi: float) -> float:
        v = self._get(key)
        if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
            raise PersistenceError(f"{self.name(key)}: expected a number, got {_kind(v)}")
        f = float(v)
        if not lo <= f <= hi:  # NaN fails too
            raise PersistenceError(f"{self.name(key)}: expected a number in [{lo:g}, {hi:g}], got {f!r}")
        return f

    def boolean(self, key: str) -> bool:
        v = self._get(key)
        if not isinstance(v, bool | np.bool_):
            raise PersistenceError(f"{self.name(key)}: expected a boolean, got {_kind(v)}")
        return bool(v)

    def choice(self, key: str, choices: Sequence[Any]) -> Any:
        v = self._get(key)
        if isinstance(v, bool) or not isinstance(v, str | int) or v not in choices:
            raise PersistenceError(f"{self.name(key)}: expected one of {list(choices)}, got {_short(v)}")
        return v

    def array(self, key: str, dtype: str, shape: Sequence[int | None]) -> np.ndarray:
        """The array under ``key``, exactly of ``dtype`` (a numpy dtype string, e.g. "<f8") and of
        ``shape`` (None: any length on that axis)."""
        a = self._get(key)
        return check_array(a, self.name(key), dtype, shape)


def check_array(a: Any, name: str, dtype: str, shape: Sequence[int | None]) -> np.ndarray:
    if not isinstance(a, np.ndarray):
        raise PersistenceError(f"{name}: expected an array, got {_kind(a)}")
    want = np.dtype(dtype)
    if a.dtype != want:
        raise PersistenceError(f"{name}: expected dtype {want.str}, got {a.dtype.str}")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise PersistenceError(f"{name}: expected shape {expected}, got {a.shape}")
    return a


def check_finite(name: str, a: np.ndarray, limit: float | None = None) -> None:
    """Every value finite (and, with ``limit``, of magnitude at most ``limit``)."""
    if a.size == 0:
        return
    if not np.all(np.isfinite(a)):
        raise PersistenceError(f"{name}: {int(np.sum(~np.isfinite(a)))} non-finite values")
    if limit is not None:
        worst = float(np.max(np.abs(a)))
        if worst > limit:
            raise PersistenceError(f"{name}: a value of magnitude {worst:.6g}, at most {limit:g} is plausible")


def check_covariances(name: str, C: np.ndarray) -> None:
    """A stack (..., d, d) of covariances: finite, symmetric, variances in [0, VARIANCE_LIMIT],
    positive semi-definite (Cholesky with a jitter of 1e-9 of the largest variance)."""
    if C.size == 0:
        return
    check_finite(name, C)
    d = C.shape[-1]
    diag = np.diagonal(C, axis1=-2, axis2=-1)
    if float(diag.min()) < 0.0:
        raise PersistenceError(f"{name}: negative variance {float(diag.min()):.6g}")
    if float(diag.max()) > VARIANCE_LIMIT:
        raise PersistenceError(f"{name}: variance {float(diag.max()):.6g}, at most {VARIANCE_LIMIT:g} is plausible")
    scale = diag.max(axis=-1)[..., None, None] + 1e-300  # (..., 1, 1) each matrix's largest variance
    with np.errstate(over="ignore"):  # an asymmetry huge against a tiny variance is inf: refused all the same
        asymmetry = float(np.max(np.abs(C - np.swapaxes(C, -1, -2)) / scale))
    if asymmetry > 1e-6:
        raise PersistenceError(f"{name}: not symmetric")
    jitter = (1e-9 * scale + 1e-12) * np.eye(d)
    try:
        np.linalg.cholesky(C + jitter)
    except np.linalg.LinAlgError:
        raise PersistenceError(f"{name}: not positive semi-definite") from None


def _kind(v: Any) -> str:
    if isinstance(v, np.ndarray):
        return f"an array {v.dtype.str} {v.shape}"
    return f"{type(v).__name__} {_short(v)}"


def _short(v: Any) -> str:
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."
