"""What this machine needs for an OAK, as ``robotd doctor`` checks it (the ``oak://`` driver's
host checks, :class:`drivers.cameras.HostCheck`): a Luxonis device on the USB bus (read from sysfs,
no lsusb needed) and a udev rule that lets a user other than root open it. Both only look."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

LUXONIS_VENDOR_ID = "03e7"
SYSFS_USB = Path("/sys/bus/usb/devices")
UDEV_RULE_DIRS = (Path("/etc/udev/rules.d"), Path("/lib/udev/rules.d"), Path("/usr/lib/udev/rules.d"))


def check_usb(url: str, sysfs_root: Path | None = None) -> tuple[bool, str]:
    """A Luxonis device (USB vendor 03e7) on the bus, read from sysfs (default :data:`SYSFS_USB`)."""
    root = SYSFS_USB if sysfs_root is None else sysfs_root
    found = []
    for vendor_file in sorted(root.glob("*/idVendor")):
        try:
            if vendor_file.read_text().strip().lower() == LUXONIS_VENDOR_ID:
                product_file = vendor_file.parent / "idProduct"
                product = product_file.read_text().strip() if product_file.exists() else "?"
                found.append(f"{vendor_file.parent.name} ({LUXONIS_VENDOR_ID}:{product})")
        except OSError:
            continue  # a device unplugged while we read: not ours to report
    if not found:
        return (
            False,
            f"no Luxonis device (USB vendor {LUXONIS_VENDOR_ID}) under {root} (camera.url={url}): "
            "plug the OAK in (USB3 port and cable), or set camera.url",
        )
    return True, f"Luxonis device on USB: {', '.join(found)}"


def check_udev(url: str, rule_dirs: Iterable[Path] | None = None) -> tuple[bool, str]:
    """A udev rule for vendor 03e7 (in :data:`UDEV_RULE_DIRS` by default): without it only root
    can open the OAK."""
    dirs = list(UDEV_RULE_DIRS if rule_dirs is None else rule_dirs)
    for d in dirs:
        for rule in sorted(d.glob("*.rules")):
            try:
                if LUXONIS_VENDOR_ID in rule.read_text(errors="replace").lower():
                    return True, f"{rule} grants access to vendor {LUXONIS_VENDOR_ID}"
            except OSError:
                continue
    return (
        False,
        f"no udev rule mentioning {LUXONIS_VENDOR_ID} in {', '.join(map(str, dirs))}: "
        "sudo cp systemd/60-robotd-oak.rules /etc/udev/rules.d/ && sudo udevadm control --reload-rules "
        "&& sudo udevadm trigger",
    )
