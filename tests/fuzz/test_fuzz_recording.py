"""Mutated recordings through the reader and the replay source (issue 15, item 5).

A small real recording (format 2, written by SessionWriter in several chunks) and a real format-1
one are damaged the ways the fault campaign found: bytes flipped, the file truncated, chunks
duplicated, record lengths and chunk sizes forged, PNG headers forged (with valid CRCs, so the
damage reaches the image decoder). Reading each through SessionReader and the ``mcap://`` replay
source must end normally or with robotd's own error type, within a time and memory bound.
"""

from __future__ import annotations

import resource
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from drivers.dataset import McapCamera
from robotd.formats.record import SessionReader
from tests.fuzz.targets import (
    FORMAT1_RECORDING,
    PNG_SIDES,
    RECORD_LENGTHS,
    duplicate_chunk,
    flip,
    forge_length,
    forge_png,
    forge_png_chunk_length,
    read_all,
    rewrite_chunk,
    small_recording,
)

RSS_GROWTH_MB = 300  # the campaign saw 4 GB for one forged PNG header
EXAMPLES = 250  # per mutation kind; the whole file runs in ~20 s on the 2-core machine


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    return {"format2": small_recording(tmp_path_factory.mktemp("fuzz")), "format1": FORMAT1_RECORDING.read_bytes()}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@pytest.fixture(scope="module", autouse=True)
def bounded_memory():
    before = _rss_mb()
    yield
    assert _rss_mb() - before < RSS_GROWTH_MB, f"peak RSS grew {_rss_mb() - before:.0f} MB while fuzzing"


FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
# (where in the file or chunk as a fraction, xor mask)
FLIPS = st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8)
WHICH = st.sampled_from(["format2", "format2", "format1"])  # the small one is cheaper: fuzzed more


@FUZZ
@given(which=WHICH, flips=FLIPS)
def test_flipped_bytes(originals, tmp_path: Path, which: str, flips: list[tuple[float, int]]) -> None:
    p = tmp_path / "m.mcap"
    p.write_bytes(flip(originals[which], flips))
    read_all(p)


@FUZZ
@given(which=WHICH, k=st.integers(0, 100), flips=FLIPS)
def test_flipped_bytes_behind_valid_crcs(originals, tmp_path: Path, which: str, k: int, flips) -> None:
    """Damage inside a chunk's messages (JSON, protobuf, PNG, base64) that its CRC does not catch:
    a writer may store no CRC, and the campaign's reader checked none."""
    p = tmp_path / "m.mcap"
    p.write_bytes(rewrite_chunk(originals[which], k, lambda raw: flip(raw, flips)))
    read_all(p)


@FUZZ
@given(which=WHICH, keep=st.floats(0, 1))
def test_truncated(originals, tmp_path: Path, which: str, keep: float) -> None:
    data = originals[which]
    p = tmp_path / "m.mcap"
    p.write_bytes(data[: int(keep * len(data))])
    read_all(p)


@FUZZ
@given(k=st.integers(0, 100), to=st.integers(0, 100))
def test_duplicated_chunks(originals, tmp_path: Path, k: int, to: int) -> None:
    p = tmp_path / "m.mcap"
    p.write_bytes(duplicate_chunk(originals["format2"], k, to))
    read_all(p)


LENGTHS = st.one_of(st.sampled_from(RECORD_LENGTHS), st.integers(0, 2**64 - 1))


@FUZZ
@given(which=WHICH, k=st.integers(0, 1000), length=LENGTHS, field=st.sampled_from(["record", "chunk-size"]))
def test_forged_lengths(originals, tmp_path: Path, which: str, k: int, length: int, field: str) -> None:
    """A record's length, or a chunk's stated uncompressed size (what a reader allocates)."""
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_length(originals[which], k, length, field))
    read_all(p)


SIDES = st.one_of(st.sampled_from(PNG_SIDES), st.integers(0, 2**32 - 1))


@FUZZ
@given(which=WHICH, k=st.integers(0, 100), w=SIDES, h=SIDES, depth=st.sampled_from([1, 8, 16]))
@example(which="format2", k=3, w=30000, h=30000, depth=8)  # under OpenCV's own 2^30-pixel cap: 900 MB
def test_forged_png_headers(originals, tmp_path: Path, which: str, k: int, w: int, h: int, depth: int) -> None:
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png(originals[which], k, w, h, depth))
    read_all(p)


@FUZZ
@given(which=WHICH, k=st.integers(0, 100), length=SIDES, chunk=st.sampled_from([b"IDAT", b"IHDR", b"IEND"]))
def test_forged_png_chunk_lengths(originals, tmp_path: Path, which: str, k: int, length: int, chunk: bytes) -> None:
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png_chunk_length(originals[which], k, length, chunk))
    read_all(p)


def test_a_forged_png_chunk_length_stops_the_read_without_allocating_it(originals, tmp_path: Path) -> None:
    """Found by bench/fuzz.py (seed 1, recording inputs 378 and 15460): an IDAT length with its top
    bits flipped (2.3 and 4.2 GB) behind valid CRCs made OpenCV allocate that much and take 6–9 s
    for one 2 kB image."""
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png_chunk_length(originals["format2"], 3, 2_332_034_984))  # chunk 3: frame 2
    before = _rss_mb()
    with McapCamera(p) as cam:
        n = sum(1 for _ in cam.frames())
        assert 0 < n < 8 and cam.reader.stopped is not None and "PNG chunk" in cam.reader.stopped, cam.reader.stopped
    assert _rss_mb() - before < 200, f"peak RSS grew {_rss_mb() - before:.0f} MB"
    r = SessionReader(p)
    assert 0 < sum(1 for _ in r.frames()) < 8
    assert r.stopped is not None and "PNG chunk IDAT at byte 33 says 2332034984 bytes" in r.stopped, r.stopped


def test_a_forged_png_header_stops_the_read_there_and_says_so(originals, tmp_path: Path) -> None:
    """The campaign's 4 GB input: an image whose header claims 65535×65535, CRCs valid."""
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png(originals["format2"], 3, 65535, 65535, 8))  # chunk 3: frame 2
    r = SessionReader(p)
    n = sum(1 for _ in r.frames())
    assert 0 < n < 8 and r.stopped is not None
    assert "PNG header says 65535x65535" in r.stopped and "the recording's camera is 64x40" in r.stopped
