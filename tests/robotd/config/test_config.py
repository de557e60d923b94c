"""Config: defaults in code, TOML overrides, errors with the dotted key path."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd.config import Config, config_from_dict, load_config, to_toml
from robotd.core.errors import ConfigError
from robotd.tools.cli import main
from tests.support.paths import REPO


def test_defaults_are_frozen_dataclasses() -> None:
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.slam.n_particles = 5  # type: ignore[misc]


def test_shipped_config_file_is_exactly_the_defaults() -> None:
    assert load_config(REPO / "config" / "robotd.toml") == Config()


def test_shipped_config_file_lists_every_key() -> None:
    # the file is the reference a user reads: a key missing there is a setting nobody finds
    shipped = tomllib.loads((REPO / "config" / "robotd.toml").read_text())
    assert shipped == tomllib.loads(to_toml(Config()))


def test_every_example_config_loads() -> None:
    for path in sorted((REPO / "config").glob("*.toml")):
        load_config(path)


def test_override_only_changes_given_keys(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[slam]\nn_particles = 42\nfilter = "ekf"\n[zenoh]\nlisten = ["tcp/127.0.0.1:7447"]\n')
    cfg = load_config(p)
    assert cfg.slam.n_particles == 42 and cfg.slam.filter == "ekf"
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7447"]
    assert cfg.frontend == Config().frontend


def test_int_is_accepted_for_float() -> None:
    assert config_from_dict({"budget": {"deadline_ms": 20}}).budget.deadline_ms == 20.0


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"slam": {"particles": 3}}, "slam.particles: unknown key"),
        ({"slm": {}}, "slm: unknown key"),
        ({"slam": {"n_particles": 0}}, "slam.n_particles: expected an integer >= 1, got 0"),
        ({"slam": {"n_particles": "many"}}, "slam.n_particles: expected an integer, got str"),
        ({"slam": {"n_particles": True}}, "slam.n_particles: expected an integer, got bool"),
        ({"slam": {"filter": "ukf"}}, "slam.filter: expected one of ['ekf', 'fastslam1', 'fastslam2'], got 'ukf'"),
        ({"slam": {"dim": 4}}, "slam.dim: expected one of [2, 3]"),
        ({"frontend": {"sigma_x_px": -1.0}}, "frontend.sigma_x_px: expected a number >= 0.01"),
        ({"zenoh": {"listen": "tcp/0.0.0.0:7447"}}, "zenoh.listen: expected a list"),
        ({"zenoh": {"listen": [7447]}}, "zenoh.listen[0]: expected a string"),
        ({"zenoh": {"enabled": "yes"}}, "zenoh.enabled: expected a boolean"),
        ({"robot": {"id": "1robot"}}, "robot.id: expected a name matching"),
        ({"slam": 3}, "slam: expected a table"),
        ({"slam": {"fs2_weights": "joint"}}, "slam.fs2_weights"),
        ({"frontend": {"cov_at": "pixels"}}, "frontend.cov_at"),
        ({"slam": {"numba_threads": -1}}, "slam.numba_threads"),
        ({"frontend": {"parallel_detect": "no"}}, "frontend.parallel_detect: expected a boolean"),
        ({"slam": {"blas_threads": 0}}, "slam.blas_threads: expected an integer >= 1, got 0"),
    ],
)
def test_bad_values_name_the_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict(data)
    assert message in str(err.value)


def test_parallel_detect_reaches_the_front_end() -> None:
    from robotd.config.params import frontend_params_from_config

    assert frontend_params_from_config(config_from_dict({})).parallel_detect is True
    one = config_from_dict({"frontend": {"parallel_detect": False}})
    assert frontend_params_from_config(one).parallel_detect is False


def test_the_pixel_measurement_model_gets_the_rig_and_the_pixel_noise() -> None:
    from robotd.config.params import slam_params_from_config
    from robotd.core.stereo import RectifiedStereo

    rig = RectifiedStereo(718.0, 607.0, 185.0, 0.54, 1241, 376)
    default = slam_params_from_config(config_from_dict({}), rig)
    assert default.measurement == "pixel" and default.stereo_intrinsics == (718.0, 607.0, 185.0, 0.54)
    cfg = config_from_dict({"slam": {"measurement": "pixel"}, "frontend": {"sigma_x_px": 0.6, "cov_inflation": 4.0}})
    p = slam_params_from_config(cfg, rig)
    assert p.measurement == "pixel" and p.stereo_intrinsics == (718.0, 607.0, 185.0, 0.54)
    assert p.pixel_sigma_px == pytest.approx((1.2, 2.0 * 0.3535533905932738))  # σ·√inflation
    with pytest.raises(ConfigError, match="slam.measurement: 'pixel' needs the stereo rig"):
        slam_params_from_config(cfg)
    with pytest.raises(ConfigError, match="slam.measurement"):
        config_from_dict({"slam": {"measurement": "pixels"}})


def test_file_errors_name_the_file(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text("[slam]\nn_particles = -3\n")
    with pytest.raises(ConfigError, match=r"slam.n_particles.*bad.toml"):
        load_config(p)
    p.write_text("[slam\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "missing.toml")


def test_to_toml_round_trips() -> None:
    cfg = config_from_dict({"slam": {"n_particles": 7}, "mavlink": {"origin_lat_deg": 52.5}})
    assert config_from_dict(tomllib.loads(to_toml(cfg, with_docs=True))) == cfg


def test_print_config_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[robot]\nid = "rover7"\n')
    assert main(["print-config", "--config", str(p)]) == 0
    out = capsys.readouterr().out
    assert 'id = "rover7"' in out and "[slam]" in out
    p.write_text("[robot]\ncolour = 1\n")
    assert main(["print-config", "--config", str(p)]) == 2
    assert "robot.colour: unknown key" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# print-config round-trips anything the loader accepts; hostile files fail in one line


@settings(max_examples=200, deadline=None)
@given(text=st.text(max_size=40))
def test_print_config_round_trips_any_string(text: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    cfg = load_config(None, {"camera": {"url": text}, "persistence": {"state_dir": text[::-1]}})
    path = tmp_path_factory.mktemp("rt") / "c.toml"
    path.write_text(to_toml(cfg, with_docs=True), encoding="utf-8")
    assert load_config(path) == cfg


def test_a_config_file_that_is_not_utf8_fails_in_one_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_bytes(b'[camera]\nurl = "sim://\xff\xfe"\n')
    with pytest.raises(ConfigError, match=r"bad.toml: not UTF-8 text \(byte 22: invalid start byte\)"):
        load_config(p)


def test_a_config_nested_too_deep_fails_in_one_line(tmp_path: Path) -> None:
    p = tmp_path / "deep.toml"
    p.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match="nested too deep|not valid TOML"):
        load_config(p)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[vehicle]\nmax_gap_s = 1" + "0" * 400 + "\n", "max_gap_s: expected a finite number, got an integer of 401"),
        ("[slam]\nn_particles = 1" + "0" * 5000 + "\n", "not valid TOML: Exceeds the limit"),
        ('["\\u000A"]\nx = 1\n', r"'\\n': unknown key in top level"),
        ("[slam]\nn_particles = 1" + "0" * 40 + "\n", "slam.n_particles = an integer of 41 digits: at most"),
    ],
)
def test_odd_documents_fail_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    # found by tests/fuzz/test_fuzz_config.py: OverflowError, ValueError, a message over two lines
    p = tmp_path / "odd.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        load_config(p)
    assert "\n" not in str(err.value) and len(str(err.value)) < 400


def test_parse_overrides_reads_toml_values_and_names_a_bad_pair() -> None:
    from robotd.config import parse_overrides

    got = parse_overrides(["slam.n_particles=50", "camera.url=sim://", "zenoh.listen=['tcp/127.0.0.1:7448']"])
    assert got["slam"] == {"n_particles": 50} and got["camera"] == {"url": "sim://"}
    assert got["zenoh"] == {"listen": ["tcp/127.0.0.1:7448"]}
    for bad in ("n_particles=50", "slam.n_particles", "slam.=1"):
        with pytest.raises(ConfigError, match="SECTION.KEY=VALUE"):
            parse_overrides([bad])
