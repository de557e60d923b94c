"""The results folder of replay-many (robotd/tools/batch/store.py): what it keeps is what the table shows."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from robotd.tools.batch import store as store_mod
from robotd.tools.batch.store import ResultStore


def test_a_ctrl_c_right_after_a_row_is_kept_loses_it_from_neither(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Ctrl-C lands just after the row was written and fsynced, before it entered the store's
    # table (as it did in a CI run under load): reload() puts the folder's rows back
    real_fsync = os.fsync

    def fsync_then_interrupt(fd: int) -> None:
        real_fsync(fd)
        raise KeyboardInterrupt

    with ResultStore(tmp_path / "out") as st:
        monkeypatch.setattr(store_mod.os, "fsync", fsync_then_interrupt)
        with pytest.raises(KeyboardInterrupt):
            st.add({"key": "k1", "status": "ok", "trajectory_text": "0 0 0 0 0 0 0 1\n"})
        monkeypatch.setattr(store_mod.os, "fsync", real_fsync)
        assert "k1" not in st.rows
        st.reload()
        assert st.rows["k1"]["status"] == "ok" and st.rows["k1"]["trajectory"].endswith("k1.txt")
    with ResultStore(tmp_path / "out") as again:  # and a new run finds it too
        assert again.done("k1") is not None
