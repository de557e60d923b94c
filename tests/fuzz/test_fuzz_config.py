"""Configuration files from hypothesis: random documents over the real keys and random ones, with
values of every TOML type (and out of every range), nesting, mutated copies of the shipped file and
raw bytes that are not UTF-8. The loader returns a Config or raises ConfigError with a one-line
message, nothing else; and whatever it accepts, ``print-config`` writes back as TOML that loads to
the same Config (tests/robotd/test_config.py covers arbitrary strings in one key; this covers whole
documents).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import tempfile
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robotd.config import Config, load_config, to_toml
from robotd.errors import ConfigError
from tests.support.paths import REPO

MAX_EXAMPLES = int(os.environ.get("ROBOTD_FUZZ_EXAMPLES", "150"))
SHIPPED = (REPO / "config" / "robotd.toml").read_text(encoding="utf-8")

SECTIONS = {f.name: [g.name for g in dataclasses.fields(getattr(Config(), f.name))] for f in dataclasses.fields(Config)}

# ------------------------------------------------------------------------- a TOML writer for the test


def _key(k: str) -> str:
    bare = k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k)
    return k if bare else _string(k)


def _string(s: str) -> str:
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04X}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, datetime.datetime | datetime.date | datetime.time):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def _document(tree: dict[str, Any]) -> str:
    lines: list[str] = []
    tables: list[tuple[str, dict[str, Any]]] = []
    for k, v in tree.items():
        if isinstance(v, dict) and v and not any(isinstance(x, dict) for x in v.values()):
            tables.append((k, v))
        else:
            lines.append(f"{_key(k)} = {_value(v)}")
    for name, body in tables:
        lines.append(f"[{_key(name)}]")
        lines += [f"{_key(k)} = {_value(x)}" for k, x in body.items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------- strategies

scalars = st.one_of(
    st.booleans(),
    st.integers(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.sampled_from((0, 1, -1, 10**20, 10**400, -(10**400))),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(("sim://", "orb", "ekf", "fastslam2", "pixel", "INFO", "tcp/127.0.0.1:7447", "r1")),
    st.datetimes(timezones=st.none()),
    st.dates(),
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8,
)
known_key = st.sampled_from(sorted(SECTIONS)).flatmap(lambda s: st.tuples(st.just(s), st.sampled_from(SECTIONS[s])))


@st.composite
def documents(draw: st.DrawFn) -> str:
    """Mostly the real keys (so that the values are converted and range-checked, not only the
    first unknown key refused), sometimes a random key or a section that is not a table."""
    wild = draw(st.integers(0, 9)) == 0
    tree: dict[str, Any] = {}
    for _ in range(draw(st.integers(0, 6))):
        section, key = draw(st.tuples(st.text(max_size=8), st.text(max_size=8)) if wild else known_key)
        body = tree.setdefault(section, {})
        if isinstance(body, dict):
            body[key] = draw(values)
    if wild and draw(st.booleans()):
        tree[draw(st.text(max_size=8) | st.sampled_from(sorted(SECTIONS)))] = draw(values)
    return _document(tree)


@st.composite
def mutated_shipped(draw: st.DrawFn) -> bytes:
    data = bytearray(SHIPPED.encode())
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data)))
        kind = draw(st.sampled_from(("insert", "delete", "replace")))
        chunk = draw(st.binary(min_size=1, max_size=6) | st.sampled_from((b"[", b"]", b'"', b"=", b"\n", b"\\u")))
        if kind == "insert":
            data[at:at] = chunk
        elif kind == "delete":
            del data[at : at + len(chunk)]
        else:
            data[at : at + len(chunk)] = chunk
    return bytes(data)


# ------------------------------------------------------------------------------------- property


def _check(blob: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.toml"
        path.write_bytes(blob)
        try:
            cfg = load_config(path)
        except ConfigError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg and "\r" not in msg, repr(msg)
            return
        out = Path(tmp) / "printed.toml"
        out.write_text(to_toml(cfg, with_docs=True), encoding="utf-8")
        assert load_config(out) == cfg


@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(doc=documents())
def test_a_random_document_loads_or_fails_in_one_line(doc: str) -> None:
    _check(doc.encode("utf-8", "surrogatepass"))


@settings(max_examples=MAX_EXAMPLES, deadline=None)
@given(blob=mutated_shipped())
def test_a_damaged_shipped_file_loads_or_fails_in_one_line(blob: bytes) -> None:
    _check(blob)


@settings(max_examples=MAX_EXAMPLES // 3, deadline=None)
@given(blob=st.binary(max_size=200))
def test_raw_bytes_load_or_fail_in_one_line(blob: bytes) -> None:
    _check(blob)
