"""The configuration reference: every key described, the page current, a misspelt key refused."""

from pathlib import Path

import pytest

from coupling.errors import ConfigError
from coupling.metrics import SteadyStateRule
from workflows.cli.main import main
from workflows.config import Config, config_from_dict
from workflows.config_reference import (
    NO_UNIT,
    PAGE_COMMAND,
    all_fields,
    config_reference,
    describe,
    reference_markdown,
)

PAGE = Path(__file__).resolve().parents[2] / "workflows" / "CONFIG.md"


def _leaf_keys(data, prefix=""):
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        if isinstance(value, dict):
            yield from _leaf_keys(value, key)
        else:
            yield key


def test_every_key_of_the_configuration_is_in_the_reference_once():
    keys = [f.key for f in all_fields()]
    assert len(keys) == len(set(keys))
    assert sorted(keys) == sorted(_leaf_keys(Config().to_dict()))


def test_every_field_has_a_description():
    undescribed = [f.key for f in all_fields() if not f.description.strip()]
    assert undescribed == []


def test_a_field_row_carries_unit_default_and_range_from_its_definition():
    (section,) = describe("dem.geometry.length_m")
    (row,) = section.fields
    assert (row.type, row.unit, row.default, row.valid) == ("float", "m", "0.33", "> 0")
    rows = {f.key: f for f in all_fields()}
    assert rows["dem.geometry.blade_azimuth_step_deg"].valid == "[0, 360)"
    assert rows["dem.geometry.blade_azimuth_step_deg"].unit == "deg"
    assert rows["dem.operation.feed_rate_total_per_s"].unit == "1/s"
    assert rows["dem.particles.density_kg_m3"].unit == "kg/m^3"
    assert rows["dem.contact.restitution"].unit == NO_UNIT and rows["dem.contact.restitution"].valid == "(0, 1]"
    assert rows["pbm.rates"].valid == 'one of "velocity", "measured", "phases"'
    assert rows["pbm.duration_s"].type == "float or unset" and rows["pbm.duration_s"].default == "unset"
    assert rows["dem.geometry.blade_pattern"].valid == "matches ^[FB]+$"


@pytest.mark.parametrize(
    "key, value, inside",
    [("window_s", 0.0, 1e-9), ("rel_tol", 0.0, 1e-9), ("rel_tol", 1.0, 0.999)],
)
def test_the_steady_state_bounds_shown_are_those_it_enforces(key, value, inside):
    """The rule is a dataclass checked in __post_init__; its reference reads "bounds" from
    the field metadata, so the two are held together here."""
    rows = {f.key: f for f in all_fields()}
    assert rows["steady_state.window_s"].valid == "> 0" and rows["steady_state.rel_tol"].valid == "(0, 1)"
    with pytest.raises(ConfigError):
        SteadyStateRule(**{key: value})
    SteadyStateRule(**{key: inside})
    with pytest.raises(ConfigError, match=f"steady_state.{key}"):
        config_from_dict({"steady_state": {key: value}})


def test_a_section_key_selects_its_fields_and_subsections():
    assert [s.key for s in describe("dem.contact")] == ["dem.contact"]
    assert [s.key for s in describe("dem")][:3] == ["dem", "dem.geometry", "dem.particles"]
    assert describe(None) == config_reference()


def test_the_checked_in_page_is_what_the_code_generates():
    assert PAGE.read_text() == reference_markdown(), f"workflows/CONFIG.md is stale; regenerate: {PAGE_COMMAND}"


def test_every_field_is_on_the_page():
    text = PAGE.read_text()
    assert all(f"| `{f.key}` |" in text for f in all_fields())


def test_cli_describe_prints_one_key(capsys):
    assert main(["config", "--describe", "dem.geometry.length_m"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[:2] == ["dem.geometry.length_m (float, m)", "    default 0.33; valid > 0"]
    assert "barrel length" in out


def test_cli_describe_markdown_is_the_page(capsys):
    assert main(["config", "--describe", "--markdown"]) == 0
    assert capsys.readouterr().out == PAGE.read_text()


@pytest.mark.parametrize(
    "key, nearest",
    [
        ("dem.geometry.lenght_m", "dem.geometry.length_m"),
        ("length_m", "dem.geometry.length_m"),
        ("dem.contact.restitutoin", "dem.contact.restitution"),
        ("steady.rel_tol", "steady_state.rel_tol"),
    ],
)
def test_cli_refuses_an_unknown_key_in_one_line_naming_the_nearest(capsys, key, nearest):
    assert main(["config", "--describe", key]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1
    assert f"unknown configuration key {key!r}" in lines[0] and nearest in lines[0]


def test_a_key_near_nothing_is_refused_listing_the_sections():
    with pytest.raises(ConfigError, match="'frobnicate'; valid sections: dem, dem.geometry"):
        describe("frobnicate")
