"""Configuration values that size memory or time are bounded by this machine and the deadline,
and the error names the key, the value, the bound and why (issue 15: ``slam.n_particles = 100000``
was accepted; RSS grew to 6 GB at 0 fps)."""

from __future__ import annotations

from pathlib import Path

import pytest

from robotd.config import Config, config_from_dict
from robotd.config import bounds as config_bounds
from robotd.core.choices import MAX_PARTICLES
from robotd.core.errors import ConfigError
from robotd.tools.cli import main

GB = 1 << 30


@pytest.fixture
def machine(monkeypatch: pytest.MonkeyPatch):
    """Set the machine's available memory (bytes) for the bounds; the real figure otherwise."""

    def set_memory(n: int) -> None:
        monkeypatch.setattr(config_bounds, "available_memory_bytes", lambda: n)

    return set_memory


def test_the_issue_case_is_refused_in_one_line_naming_the_key_the_bound_and_the_machine() -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict({"slam": {"n_particles": 100000}})
    msg = str(err.value)
    assert msg.startswith("slam.n_particles = 100000: at most ") and "\n" not in msg
    assert "GB available, 33.3 ms deadline)" in msg
    real = config_bounds.available_memory_bytes()
    assert f"({real / 1e9:.1f} GB available" in msg


def test_print_config_refuses_it_with_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "big.toml"
    p.write_text("[slam]\nn_particles = 100000\n")
    assert main(["print-config", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("robotd: error: slam.n_particles = 100000: at most") and err.endswith("(in " + str(p) + ")")
    assert len(err.splitlines()) == 1


def test_particles_are_bounded_by_the_deadline(machine) -> None:
    machine(64 * GB)
    # 10 ms at 0.271 µs per particle and observation, 80 + 40 observations a frame: 307 particles
    cfg = {"budget": {"deadline_ms": 10.0}}
    assert config_from_dict({**cfg, "slam": {"n_particles": 307}}).slam.n_particles == 307
    with pytest.raises(ConfigError, match=r"slam.n_particles = 308: at most 307 .*10.0 ms deadline.*µs per particle"):
        config_from_dict({**cfg, "slam": {"n_particles": 308}})
    # fewer observations a frame, or a longer deadline (an offline run), allow more
    fewer = {"slam": {"n_particles": 600, "max_updates_per_frame": 40, "max_new_per_frame": 20}}
    assert config_from_dict({**cfg, **fewer}).slam.n_particles == 600
    assert config_from_dict({"budget": {"deadline_ms": 20.0}, "slam": {"n_particles": 600}}).slam.n_particles == 600
    # FastSLAM 1.0 costs less per particle
    assert config_from_dict({**cfg, "slam": {"n_particles": 500, "filter": "fastslam1"}}).slam.filter == "fastslam1"


def test_particles_are_bounded_by_the_memory(machine) -> None:
    machine(1 * GB)
    # half of 1 GiB over 10 000 landmarks × 96 B per particle (3-D): 559 particles
    slow = {"budget": {"deadline_ms": 1000.0}}
    assert config_from_dict({**slow, "slam": {"n_particles": 559}}).slam.n_particles == 559
    with pytest.raises(ConfigError, match=r"n_particles = 560: at most 559 on this machine \(1.1 GB available.*memory"):
        config_from_dict({**slow, "slam": {"n_particles": 560}})
    # a planar map's landmark is half the size
    assert config_from_dict({**slow, "slam": {"n_particles": 1000, "dim": 2}}).slam.n_particles == 1000


def test_particles_have_a_fixed_ceiling(machine) -> None:
    machine(1 << 50)
    slow = {"budget": {"deadline_ms": 1e6}}
    assert config_from_dict({**slow, "slam": {"n_particles": MAX_PARTICLES}}).slam.n_particles == MAX_PARTICLES
    with pytest.raises(ConfigError, match=f"at most {MAX_PARTICLES} .*the fixed ceiling"):
        config_from_dict({**slow, "slam": {"n_particles": MAX_PARTICLES + 1}})


def test_the_ekf_has_no_particles_to_bound(machine) -> None:
    machine(1 * GB)
    assert config_from_dict({"slam": {"filter": "ekf", "n_particles": 100000}}).slam.filter == "ekf"


def test_features_are_bounded_by_the_memory_of_the_frame_to_frame_match(machine) -> None:
    machine(1 * GB)
    # half of 1 GiB at 16 B per pair of features: isqrt(2**25) = 5792
    assert config_from_dict({"frontend": {"max_features": 5792}}).frontend.max_features == 5792
    with pytest.raises(ConfigError, match=r"frontend.max_features = 5793: at most 5792 on this machine"):
        config_from_dict({"frontend": {"max_features": 5793}})


def test_the_defaults_fit_a_1_gb_board(machine) -> None:
    machine(1 * GB)
    assert config_from_dict({}) == Config()


def test_the_memory_reading_falls_back_to_the_physical_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    real_open = open

    def no_proc(path, *a, **k):
        if str(path) == "/proc/meminfo":
            raise FileNotFoundError(path)
        return real_open(path, *a, **k)

    config_bounds.available_memory_bytes.cache_clear()
    monkeypatch.setattr("builtins.open", no_proc)
    try:
        import os

        assert config_bounds.available_memory_bytes() == os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    finally:
        config_bounds.available_memory_bytes.cache_clear()
