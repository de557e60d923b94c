"""Short replay sources for the replay-many tests: simulated drives of a couple of seconds at a low
resolution and frame rate (different seeds and worlds), recordings written by the recording writer
from such drives, a damaged recording, and the small shared sequences when ../shared/data is there."""

from __future__ import annotations

import os
from pathlib import Path

SMALL = "duration=2&realtime=0&width=160&height=100&fps=5"


def sim_url(seed: int, world: str = "yard", extra: str = "") -> str:
    return f"sim://{world}?{SMALL}&seed={seed}" + (f"&{extra}" if extra else "")


def write_recording(path: Path, seed: int, max_frames: int = 10) -> Path:
    """A robotd recording (MCAP) of a short simulated drive, written by the recording writer."""
    import drivers
    from robotd.formats.record import SessionWriter, record_session

    url = sim_url(seed)
    with drivers.open_camera(url) as cam, drivers.open_vehicle(url) as veh:
        with SessionWriter(path, cam.rectified_model(), {"source": url, "seed": seed}) as w:
            record_session(cam, veh, w, duration_s=0, max_frames=max_frames)
    return path


def shared_data_root() -> Path:
    from tests.support.paths import REPO

    return Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_sources(stop: int = 8) -> list[str]:
    """The KITTI and EuRoC sequences of ../shared/data, cut to ``stop`` frames ([] when absent)."""
    root = shared_data_root()
    out: list[str] = []
    for scheme, name in (("kitti", "kitti-seq1"), ("euroc", "euroc-v101-micro")):
        if (root / name).is_dir():
            out.append(f"{scheme}://{(root / name).resolve()}?stop={stop}")
    return out


def fleet_sources(tmp: Path) -> tuple[list[str], str]:
    """At least 20 working sources (sim seeds and worlds, two recordings, the shared sequences or more
    sim seeds in their place) and a damaged recording; returns (working, damaged)."""
    sims = [sim_url(s) for s in range(1, 13)]
    sims += [sim_url(13, "turn_in_place"), sim_url(14, "moving_box"), sim_url(15, "low_texture")]
    sims += [sim_url(16, extra="odometry=0")]  # vision only
    recs = [str(write_recording(tmp / f"rec-{s}.mcap", s)) for s in (21, 22)]
    shared = shared_sources()
    extra = [sim_url(30 + k) for k in range(2 - len(shared))]  # without ../shared/data: as many sim drives
    damaged = tmp / "damaged.mcap"
    damaged.write_bytes(b"\x89MCAP0\r\n" + os.urandom(4096))
    return [*sims, *recs, *shared, *extra], str(damaged)
