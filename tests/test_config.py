"""Configuration: presets load, every bad value is refused with its key and range named."""

import pytest

from coupling.errors import ConfigError
from workflows.cli import main
from workflows.config import config_from_dict, dump_toml, load_config, load_preset, preset_names


@pytest.mark.parametrize("name", ["paper", "reduced", "smoke"])
def test_presets_load_and_round_trip_through_toml(tmp_path, name):
    config = load_preset(name)
    assert config.name == name
    path = tmp_path / "c.toml"
    path.write_text(dump_toml(config))
    assert load_config(path) == config


def test_paper_preset_is_table_1():
    dem = load_preset("paper").dem
    assert dem.particles.youngs_modulus_pa == pytest.approx(2 * 2e6 * 1.33)
    assert dem.steel.youngs_modulus_pa == pytest.approx(2 * 7.93e10 * 1.33)
    assert dem.operation.feed_rate_total_per_s == 1990 and dem.operation.impeller_rpm == 250
    assert dem.contact.friction_particle_particle == 0.5 and dem.contact.friction_particle_wall == 0.4
    # Rayleigh time of a 2 mm particle is about 9.3e-5 s; ours uses the smallest one.
    assert 7e-5 < dem.rayleigh_time_s < 9.3e-5


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"dem": {"geometry": {"lenght_m": 1}}}, "did you mean 'length_m'"),
        ({"dem": {"geometry": {"length_m": -1}}}, "'dem.geometry.length_m' = -1"),
        ({"dem": {"geometry": {"diameter_m": 0}}}, "'dem.geometry.diameter_m' = 0"),
        ({"dem": {"operation": {"impeller_rpm": 0}}}, "'dem.operation.impeller_rpm' = 0"),
        ({"dem": {"operation": {"feed_rate_total_per_s": -5}}}, "feed_rate_total_per_s"),
        ({"dem": {"numerics": {"timestep_rayleigh_fraction": 0.4}}}, "above the stable limit 0.27"),
        ({"dem": {"numerics": {"seed": 20000}}}, "not prime"),
        ({"dem": {"geometry": {"blade_tip_clearance_m": 0.001}}}, "pinched"),
        ({"dem": {"tables": {"nx": 0}}}, "'dem.tables.nx' = 0"),
        ({"pbm": {"noise_sigma": -0.1}}, "'pbm.noise_sigma' = -0.1"),
    ],
)
def test_bad_values_are_refused_by_name(data, fragment):
    with pytest.raises(ConfigError) as info:
        config_from_dict(data)
    assert fragment in str(info.value)


def test_unknown_preset_lists_the_valid_ones():
    with pytest.raises(ConfigError, match="valid presets: paper, reduced, smoke.*did you mean 'smoke'"):
        load_preset("smok")


def test_cli_config_prints_preset_and_reports_errors(capsys, tmp_path):
    assert main(["config", "--list"]) == 0
    assert capsys.readouterr().out.split() == preset_names()
    bad = tmp_path / "bad.toml"
    bad.write_text("[dem.operation]\nimpeller_rpm = -3\n")
    assert main(["config", "--config", str(bad)]) == 2
    assert "impeller_rpm" in capsys.readouterr().err
