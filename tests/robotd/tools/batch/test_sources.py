"""replay-many's sources and configurations (robotd/tools/batch/sources.py, configs.py): what an argument
names, and digests that change exactly when the data or the settings do."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from robotd.core.errors import InputError
from robotd.tools.batch.configs import build_configurations, parse_variant
from robotd.tools.batch.sources import DigestCache, expand_sources, source_digest


def _kitti(root: Path) -> Path:
    (root / "image_0").mkdir(parents=True)
    (root / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (root / "times.txt").write_text("0.0\n0.1\n")
    for k in range(2):
        (root / "image_0" / f"{k:06d}.png").write_bytes(bytes([k]) * 100)
    return root


def test_arguments_name_recordings_folders_globs_and_urls(tmp_path: Path) -> None:
    kitti = _kitti(tmp_path / "seq")
    (tmp_path / "euroc" / "mav0" / "cam0").mkdir(parents=True)
    (tmp_path / "euroc" / "mav0" / "cam1").mkdir(parents=True)
    arch = tmp_path / "archive"
    arch.mkdir()
    for n in ("b.mcap", "a.mcap", "notes.txt"):
        (arch / n).write_bytes(b"x")
    lst = tmp_path / "list.txt"
    lst.write_text(f"# the archive\n\n{arch}/b.mcap\n")
    got = expand_sources(
        [str(kitti), str(tmp_path / "euroc"), str(arch), f"{tmp_path}/arch*/a.mcap", "sim://?seed=3"], [lst]
    )
    assert [s.url for s in got] == [
        f"kitti://{kitti}",
        f"euroc://{tmp_path / 'euroc'}",
        str(arch / "a.mcap"),
        str(arch / "b.mcap"),
        "sim://?seed=3",
    ]  # each once, in order
    assert [s.name for s in got][:3] == ["seq", "euroc", "a.mcap"]
    assert [s.url for s in expand_sources([f"kitti://{tmp_path}/se*?stop=1"])] == [f"kitti://{kitti}?stop=1"]
    for bad, msg in (
        ("oak://", "unknown scheme 'oak'"),
        (str(tmp_path / "none-*"), "no file or folder matches"),
        (str(lst), "is not a recording"),
        (str(tmp_path / "euroc" / "mav0" / "cam0"), "neither a KITTI folder"),
    ):
        with pytest.raises(InputError, match=msg):
            expand_sources([bad])


def test_a_recording_digest_is_its_content_and_is_computed_once(tmp_path: Path) -> None:
    rec = tmp_path / "r.mcap"
    rec.write_bytes(b"a" * 10_000)
    cache = DigestCache(tmp_path / "digests.json")
    d1 = source_digest(str(rec), cache)
    assert source_digest(str(rec), cache) == d1 and cache.hashed == 1  # the second from the cache
    cache.save()
    again = DigestCache(tmp_path / "digests.json")
    assert source_digest(str(rec), again) == d1 and again.hashed == 0  # a rerun reads it no more
    rec.write_bytes(b"a" * 9_999 + b"b")  # one byte
    assert source_digest(str(rec), again) != d1
    copy = tmp_path / "elsewhere.mcap"
    shutil.copy(rec, copy)
    assert source_digest(str(copy)) == source_digest(str(rec))  # the content, not the path
    assert source_digest(f"mcap://{rec}?stop=5") != source_digest(str(rec))  # the selection counts


def test_a_folder_digest_follows_its_listing_and_index_files_wherever_it_lies(tmp_path: Path) -> None:
    seq = _kitti(tmp_path / "seq")
    d = source_digest(f"kitti://{seq}")
    moved = tmp_path / "moved"
    shutil.copytree(seq, moved)  # copy2: sizes and mtimes kept
    assert source_digest(f"kitti://{moved}") == d
    times = moved / "times.txt"
    st = times.stat()
    times.write_text("0.0\n0.2\n")  # same size and mtime: the index file's content still counts
    os.utime(times, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert source_digest(f"kitti://{moved}") != d
    img = seq / "image_0" / "000001.png"
    os.utime(img, ns=(img.stat().st_atime_ns, img.stat().st_mtime_ns + 1))  # an image touched
    assert source_digest(f"kitti://{seq}") != d
    assert source_digest("sim://yard?seed=2&duration=3") == source_digest("sim://yard?duration=3&seed=2")
    assert source_digest("sim://yard?seed=2") != source_digest("sim://yard?seed=3")


def test_configurations_are_files_times_variants_with_digests_of_their_settings(tmp_path: Path) -> None:
    assert parse_variant('ekf: slam.filter="ekf" frontend.detector=sift') == (
        "ekf",
        ['slam.filter="ekf"', "frontend.detector=sift"],
    )
    assert parse_variant("slam.n_particles=50")[0] == "slam.n_particles=50"
    a = tmp_path / "a.toml"
    a.write_text("[slam]\nn_particles = 50\n")
    b = tmp_path / "b.toml"
    b.write_text("[slam]\nn_particles = 50\n[robot]\nseed = 1\n")  # seed 1 is the default: same settings
    cs = build_configurations([str(a), str(b)], ["robot.seed=1"], ["x: slam.dim=2", "y: slam.dim=3"])
    assert [c.name for c in cs] == ["a/x", "a/y", "b/x", "b/y"]
    assert cs[0].digest == cs[2].digest and cs[0].digest != cs[1].digest
    assert cs[0].config().slam.dim == 2 and cs[0].config().slam.n_particles == 50
    with pytest.raises(InputError, match="named alike"):
        build_configurations([], [], ["x: slam.dim=2", "x: slam.dim=3"])
    with pytest.raises(InputError, match="expected SECTION.KEY=VALUE"):
        build_configurations([], ["nonsense"])
