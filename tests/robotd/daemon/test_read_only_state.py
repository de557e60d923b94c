"""A map that cannot be resumed, in a state directory the daemon cannot write (a read-only
filesystem): the daemon starts with a new map, says in one line that the old one was left in place
and ignored, never writes over it, and says that it cannot save. Run as a real ``robotd run`` with
the state directory really read-only (a read-only bind mount in a user namespace when run as root,
whom file modes do not stop)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO
from tests.support.saved_maps import saved_state, seal


def _read_only_prefix(directory: Path) -> list[str]:
    """The argv prefix that runs a command with ``directory`` read-only."""
    if os.geteuid() != 0:
        directory.chmod(0o555)
        return []
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" && shift && exec "$@"'
    prefix = ["unshare", "-rm", "sh", "-c", script, "sh", str(directory)]
    if shutil.which("unshare") is None or subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:
        pytest.skip("running as root without user namespaces: cannot make a directory read-only")
    return prefix


@pytest.mark.parametrize("damage", ["checksum", "content"])
def test_a_bad_map_in_a_read_only_state_dir_is_ignored_and_never_overwritten(tmp_path: Path, damage: str) -> None:
    state_dir = tmp_path / "state"
    state_dir.mkdir()
    state = saved_state()
    if damage == "content":
        del state["estimator"]["lm_cov"]  # valid checksum, a key missing
    blob = bytearray(seal(state))
    if damage == "checksum":
        blob[100] ^= 0xFF
    (state_dir / "map.robotd").write_bytes(blob)
    config = tmp_path / "robotd.toml"
    config.write_text(
        f"""[camera]
url = "sim://?fps=20"
[vehicle]
url = "sim://?fps=20"
[zenoh]
enabled = false
[persistence]
state_dir = "{state_dir}"
resume = true
save_period_s = 1.0
"""
    )
    argv = [sys.executable, "-m", "robotd", "run", "--config", str(config), "--duration", "4"]
    proc = subprocess.run([*_read_only_prefix(state_dir), *argv], cwd=REPO, capture_output=True, text=True, timeout=180)
    err = proc.stderr
    assert "Traceback" not in err, err[-3000:]
    assert proc.returncode == 0, err[-3000:]
    failed = [line for line in err.splitlines() if "resume failed" in line]
    assert len(failed) == 1, err[-3000:]
    assert "could not move it aside (Read-only file system): left in place and ignored" in failed[0]
    assert "the map there failed to resume" in err and "so it is not written over" in err
    assert "map saved" not in err
    assert (state_dir / "map.robotd").read_bytes() == bytes(blob)
    assert sorted(p.name for p in state_dir.iterdir()) == ["map.robotd"]
