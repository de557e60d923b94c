"""Configuration files from hypothesis: random documents over the real keys and random ones, with
values of every TOML type (and out of every range), nesting, mutated copies of the shipped file and
raw bytes that are not UTF-8. The loader returns a Config or raises ConfigError with a one-line
message, nothing else; and whatever it accepts, ``print-config`` writes back as TOML that loads to
the same Config (tests/robotd/config/test_config.py covers arbitrary strings in one key; this covers whole
documents).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fuzz.targets import CONFIG_TOKENS, SHIPPED_CONFIG, Drawn, check_config, config_sections, damage_text
from tests.fuzz.targets import toml_document as _document

MAX_EXAMPLES = int(os.environ.get("ROBOTD_FUZZ_EXAMPLES", "150"))
SECTIONS = config_sections()

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
    c = Drawn(draw)
    chunk = st.binary(min_size=1, max_size=6) | st.sampled_from(CONFIG_TOKENS[:6])
    return damage_text(SHIPPED_CONFIG.encode(), c, c.randint(1, 4), lambda: draw(chunk))


def _check(blob: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        check_config(blob, Path(tmp))


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
