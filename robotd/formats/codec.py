"""Compact, versioned, language-neutral encodings (CBOR, RFC 8949) for maps and saved state.

Arrays travel as a CBOR map ``{"dtype": "<f8", "shape": [M, 3], "data": bytes}`` with a
little-endian numpy dtype string, so any CBOR library (Python cbor2, C tinycbor, Rust ciborium,
JavaScript cbor-x) reads them without robotd. The map message layout is documented in
docs/topics.md.
"""

from __future__ import annotations

from typing import Any

import cbor2
import numpy as np

from robotd.core.errors import PersistenceError
from robotd.core.msgs import LandmarkMap

MAP_SCHEMA = "robotd.map/1"


def pack_array(a: np.ndarray) -> dict[str, Any]:
    a = np.ascontiguousarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    return {"dtype": dt.str, "shape": list(a.shape), "data": a.astype(dt, copy=False).tobytes()}


def unpack_array(d: Any, name: str = "array") -> np.ndarray:
    try:
        dt = np.dtype(d["dtype"])
        shape = tuple(int(s) for s in d["shape"])
        data = d["data"]
        if dt.hasobject:
            raise ValueError("object arrays are not allowed")
        a = np.frombuffer(data, dtype=dt)
        return a.reshape(shape).copy()
    except (KeyError, TypeError, ValueError, AttributeError, SyntaxError, OverflowError, MemoryError) as exc:
        # numpy raises any of these for a forged dtype string or shape
        raise PersistenceError(f"{name}: not a packed array ({type(exc).__name__}: {exc})") from None


def pack_tree(obj: Any) -> Any:
    """Recursively pack numpy arrays and scalars inside dicts/lists for CBOR."""
    if isinstance(obj, np.ndarray):
        return {"__nd__": pack_array(obj)}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {str(k): pack_tree(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [pack_tree(v) for v in obj]
    return obj


def unpack_tree(obj: Any, name: str = "state") -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__nd__"}:
            return unpack_array(obj["__nd__"], name)
        return {k: unpack_tree(v, f"{name}.{k}") for k, v in obj.items()}
    if isinstance(obj, list):
        return [unpack_tree(v, name) for v in obj]
    return obj


def encode_map(robot_id: str, t_ns: int, lm: LandmarkMap, seq: int = 0) -> bytes:
    """The published map: ids int64, xyz float32 (M, 3) metres in the world frame (LOCAL_FRD),
    cov float32 (M, 6) upper triangle (xx, xy, xz, yy, yz, zz) in m²."""
    iu = np.triu_indices(3)
    cov6 = lm.cov_W[:, iu[0], iu[1]].astype("<f4")
    msg = {
        "schema": MAP_SCHEMA,
        "robot": robot_id,
        "t_ns": int(t_ns),
        "seq": int(seq),
        "frame": "LOCAL_FRD",
        "n": lm.n,
        "ids": pack_array(lm.ids.astype("<i8")),
        "xyz_m": pack_array(lm.xyz_W_m.astype("<f4")),
        "cov_m2_upper": pack_array(cov6),
    }
    return cbor2.dumps(msg)


def decode_map(data: bytes) -> tuple[dict[str, Any], LandmarkMap]:
    try:
        msg = cbor2.loads(data)
    except Exception as exc:  # cbor2 raises several types on garbage
        raise PersistenceError(f"map message is not CBOR: {exc}") from exc
    if not isinstance(msg, dict) or msg.get("schema") != MAP_SCHEMA:
        got = msg.get("schema") if isinstance(msg, dict) else type(msg).__name__
        raise PersistenceError(f"map message: expected schema {MAP_SCHEMA!r}, got {got!r}")
    ids = unpack_array(msg["ids"], "ids").astype(np.int64)
    xyz = unpack_array(msg["xyz_m"], "xyz_m").astype(float)
    c6 = unpack_array(msg["cov_m2_upper"], "cov_m2_upper").astype(float)
    cov = np.zeros((len(ids), 3, 3))
    iu = np.triu_indices(3)
    cov[:, iu[0], iu[1]] = c6
    cov[:, iu[1], iu[0]] = c6
    meta = {k: v for k, v in msg.items() if k not in ("ids", "xyz_m", "cov_m2_upper")}
    return meta, LandmarkMap(ids, xyz, cov)
