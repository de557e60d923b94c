"""The OAK's host checks (drivers/oak/host.py, ``robotd doctor``'s oak-usb and oak-udev): a fake
sysfs tree and udev rule directories, with and without the Luxonis device and the shipped rule."""

from __future__ import annotations

from pathlib import Path

from drivers.oak.host import check_udev, check_usb
from tests.robotd.tools.test_doctor import fake_sysfs
from tests.support.paths import REPO


def test_usb_finds_the_luxonis_vendor_in_sysfs(tmp_path: Path) -> None:
    hub = {"usb1": ("1d6b", "0002")}
    present = fake_sysfs(tmp_path / "a", {**hub, "1-1": ("03e7", "2485")})
    absent = fake_sysfs(tmp_path / "b", hub)
    ok, message = check_usb("oak://", present)
    assert ok and "1-1 (03e7:2485)" in message
    ok, message = check_usb("oak://", absent)
    assert not ok and "03e7" in message and "camera.url" in message


def test_udev_rule_from_the_shipped_file(tmp_path: Path) -> None:
    (tmp_path / "rules").mkdir()
    (tmp_path / "rules" / "99-other.rules").write_text('SUBSYSTEM=="tty", GROUP="dialout"\n')
    assert not check_udev("oak://", [tmp_path / "rules", tmp_path / "missing"])[0]
    shipped = REPO / "systemd" / "60-robotd-oak.rules"
    (tmp_path / "rules" / shipped.name).write_text(shipped.read_text())
    ok, message = check_udev("oak://", [tmp_path / "missing", tmp_path / "rules"])
    assert ok and shipped.name in message
