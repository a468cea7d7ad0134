"""Configuration: presets load, every bad value is refused with its key and range named."""

import pytest

from coupling.errors import ConfigError
from workflows.cli.main import main
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


def _float_keys(model, prefix=()):
    """Dotted keys of every float field of the configuration, nested sections included."""
    import dataclasses
    import typing

    from pydantic import BaseModel

    fields = (
        {name: f.annotation for name, f in model.model_fields.items()}
        if issubclass(model, BaseModel)
        else typing.get_type_hints(model)  # resolves the dataclass's string annotations
    )
    for name, annotation in fields.items():
        if isinstance(annotation, type) and (issubclass(annotation, BaseModel) or dataclasses.is_dataclass(annotation)):
            yield from _float_keys(annotation, (*prefix, name))
        elif annotation is float or float in typing.get_args(annotation):
            yield (*prefix, name)


def _nested(key, value):
    data = value
    for part in reversed(key):
        data = {part: data}
    return data


def test_every_float_key_refuses_inf_and_nan():
    from workflows.config import Config

    keys = list(_float_keys(Config))
    assert len(keys) > 40 and ("steady_state", "rel_tol") in keys and ("pbm", "duration_s") in keys
    accepted = []
    for key in keys:
        for value in (float("inf"), float("-inf"), float("nan")):
            try:
                config_from_dict(_nested(key, value))
            except ConfigError as exc:
                assert f"'{'.'.join(key)}' = {value!r}: Input should be a finite number" in str(exc)
            else:
                accepted.append((".".join(key), value))
    assert accepted == []


@pytest.mark.parametrize(
    "section, line",
    [
        ("dem.operation", "feed_rate_total_per_s = inf"),
        ("dem.operation", "duration_s = +inf"),
        ("dem.geometry", "feed_height_m = nan"),
        ("dem.particles", "diameter_m = nan"),
        ("dem.numerics", "dump_interval_s = inf"),
        ("dem.tables", "window_s = -inf"),
        ("pbm", "bdf_rtol = nan"),
        ("pbm", "duration_s = inf"),
        ("steady_state", "window_s = inf"),
        ("steady_state", "rel_tol = nan"),
    ],
)
def test_inf_and_nan_in_a_toml_file_are_refused_by_key(tmp_path, section, line):
    path = tmp_path / "c.toml"
    path.write_text(f"[{section}]\n{line}\n")
    key = line.split(" = ")[0]
    with pytest.raises(ConfigError, match=rf"'{section}\.{key}' = .*(inf|nan).*finite number"):
        load_config(path)


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n# and another\n"])
def test_empty_config_file_is_refused_with_how_to_start(tmp_path, text):
    path = tmp_path / "empty.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message and "sets no keys" in message
    assert "pbmdem config --preset reduced > my.toml" in message


def test_binary_config_file_is_a_one_line_error(tmp_path):
    path = tmp_path / "blob.toml"
    path.write_bytes(b'name = "x"\n\xff\xfe\x00\x89PNG\r\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "not a UTF-8 text file" in message


def test_a_byte_order_mark_is_read_past_and_a_device_is_no_config(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + dump_toml(load_preset("validation")).encode())
    assert load_config(path) == load_preset("validation")
    with pytest.raises(ConfigError, match="/dev/null is not a regular file"):
        load_config("/dev/null")


def test_a_key_under_the_wrong_table_is_told_where_it_belongs(tmp_path):
    path = tmp_path / "wrong.toml"
    path.write_text("[dem.geometry]\nimpeller_rpm = 300.0\nseed = 3\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "'dem.geometry.impeller_rpm' (it belongs in [dem.operation])" in str(err.value)
    assert "'dem.geometry.seed' (it belongs in [dem.numerics] or [pbm])" in str(err.value)


def test_config_path_that_is_a_directory(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)


def test_cli_reports_empty_config_without_traceback(capsys, tmp_path):
    path = tmp_path / "empty.toml"
    path.write_text("# nothing yet\n")
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "--preset reduced" in err and "Traceback" not in err


# ----------------------------------------------------------------------------- issue 22: strict types
@pytest.mark.parametrize(
    ("assignment", "message"),
    [
        ('dem.tables.nx="10"', r"'dem\.tables\.nx' = '\"10\"' \(text\): an integer is needed"),
        ("dem.run.np=true", r"'dem\.run\.np' = true \(a boolean\): an integer is needed"),
        ("dem.operation.duration_s=true", r"'dem\.operation\.duration_s' = true \(a boolean\): a number is needed"),
        ("dem.tables.nx=1e9", r"'dem\.tables\.nx' = 1000000000\.0 \(a float\): an integer is needed"),
        ("pbm.seed=false", r"'pbm\.seed' = false \(a boolean\): an integer is needed"),
        ("pbm.feed_rate_a_per_s=true", r"'pbm\.feed_rate_a_per_s' = true \(a boolean\)"),
        ("steady_state.window_s=true", r"steady_state\.window_s = true \(a boolean\): a number is needed"),
        ("dem.run.launcher=mpirun -np {n}", r"uses the unknown field \{n\}; the only field is \{np\}"),
        ("dem.run.launcher=mpirun -np {np", r"is not a valid template \(expected '\}' before end of string\)"),
        ("dem.run.launcher=mpirun -np {np:d}", r"has a conversion or format spec; write it as plain \{np\}"),
        ('dem.run.launcher=mpirun "-np {np}', r"is not a valid command line \(No closing quotation\)"),
        ("dem.run.launcher=srun {}", r"uses the unknown field \{\}"),
        ("dem.run.liggghts=", r"'dem\.run\.liggghts' = '': is empty; the LIGGGHTS command is needed"),
        ("dem.run.liggghts=   ", r"is empty"),
    ],
)
def test_loose_types_and_bad_launcher_templates_are_refused_by_key(assignment, message):
    from workflows.config import override

    with pytest.raises(ConfigError, match=message):
        override(load_preset("smoke"), assignment)


def test_strict_types_in_a_toml_file_and_what_stays_valid(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('name = "x"\n[dem.tables]\nnx = "10"\n[dem.run]\nnp = true\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "'dem.tables.nx' = '10' (text)" in str(info.value) and "'dem.run.np' = true (a boolean)" in str(info.value)
    path.write_text(
        'name = "x"\n[dem.operation]\nduration_s = 10\n[dem.run]\nlauncher = "srun"\n'
        'liggghts = "liggghts -echo screen"\n[pbm]\nfeed_rate_a_per_s = 3\n'
    )
    config = load_config(path)  # an integer where a float belongs is a number
    assert config.dem.operation.duration_s == 10.0 and config.dem.run.launcher == "srun"
    from dem.config import check_launcher

    assert check_launcher("mpirun --map-by {{core}} -np {np}") == "mpirun --map-by {{core}} -np {np}"
    assert check_launcher("") == ""


# ----------------------------------------------------------------------------- issue 22: degenerate inputs
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"seed": -1}, r"seed must be an integer >= 0"),
        ({"seed": 1.5}, r"seed must be an integer >= 0"),
        ({"n_windows": 10**8}, r"a synthetic table of 100000000 windows .* needs about .* of memory"),
        ({"n_windows": 0}, r"n_windows \(--windows\) must be an integer >= 1"),
        ({"window_s": float("nan")}, r"window_s must be a finite number > 0, got nan"),
        ({"n_windows": 10**6, "window_s": 1e4}, r"must stay within 1e\+09 s"),
    ],
)
def test_synthetic_table_refuses_bad_seeds_and_window_counts(kwargs, message):
    from coupling.errors import PbmDemError
    from pbm.synthetic import synthetic_table

    with pytest.raises(PbmDemError, match=message) as info:
        synthetic_table(**kwargs)
    assert "\n" not in str(info.value)


def test_memory_estimates_refuse_what_the_machine_cannot_hold():
    from coupling.errors import ResourceLimitError
    from pbm.config import PbmConfig
    from pbm.ensemble import noise_ensemble
    from pbm.resources import check_ensemble_memory, check_pbm_memory
    from pbm.synthetic import synthetic_table

    with pytest.raises(ResourceLimitError, match=r"ensemble of 100000000 members .* at most \d+ members fit"):
        noise_ensemble(synthetic_table(n_windows=4), PbmConfig(noise_sigma=0.1), members=100_000_000)
    assert check_ensemble_memory(200, 260.0, 1.0, 1.0, 10) < 50e6  # the paper's study: a few MB
    with pytest.raises(ResourceLimitError, match=r"the PBM on 100000 x 10 compartments .* use a coarser grid"):
        check_pbm_memory(100_000, 10, 52)
    assert check_pbm_memory(10, 10, 52) < 100e6
    with pytest.raises(ResourceLimitError, match=r"needs about 1\.7 KiB of memory; this machine has 100 B available"):
        check_pbm_memory(1, 1, 1, available_bytes=100)


def test_memory_estimate_counts_the_hidden_phases():
    """A phase model multiplies the states by K (the issue's K = 480 table on 10 x 10 took 19
    of 23 GB unrefused): the estimate counts NX*NY*K populations, one generator."""
    from coupling.errors import ResourceLimitError
    from pbm.resources import check_pbm_memory, pbm_bytes

    assert pbm_bytes(10, 10, 64, n_phases=3) < 50e6  # the shipped K = 3 model: tens of MB
    assert pbm_bytes(10, 10, 64, n_phases=480) > 100 * 2**30  # 48003 states: a dense operator is 17 GiB
    with pytest.raises(
        ResourceLimitError,
        match=r"the PBM on 10 x 10 compartments with 480 phases each \(48000 populations\) over 64 velocity windows "
        r"needs about 206\.2 GiB of memory; this machine has 1\.9 GiB available .* one dense 48003 x 48003 operator "
        r"is 17\.2 GiB; use a phase model with fewer phases or a coarser grid",
    ):
        check_pbm_memory(10, 10, 64, available_bytes=2e9, n_phases=480)
    check_pbm_memory(10, 10, 64, available_bytes=2e9, n_phases=3)


def test_pbm_run_refuses_a_phase_table_too_large_before_writing(tmp_path, monkeypatch, capsys):
    import numpy as np

    from coupling.phases import PhaseTransport
    from coupling.tables import make_table, write_table
    from workflows.cli.main import main

    k, nx = 200, 10
    rates = np.zeros((k, 4, nx, 1))
    rates[:, 0], rates[:, 1] = 2.0, 0.5
    model = PhaseTransport(rates, np.zeros((k, k, nx, 1)), np.full((2, k), 1.0 / k), 0.1)
    table = make_table(np.arange(0.0, 50.0, 5.0), np.linspace(0, 0.33, nx + 1), [-0.05, 0.05], 0.01, 0.01, 0.0, 0.0)
    path = write_table(tmp_path / "k200.h5", table.replace(phases=model))
    monkeypatch.setenv("PBMDEM_MEMORY_BYTES", "100000000")
    out = tmp_path / "out"
    argv = ["pbm", "run", "--tables", str(path), "--preset", "smoke", "--out", str(out)]
    assert main([*argv, "--rates", "phases"]) == 2
    err = capsys.readouterr().err
    assert "with 200 phases each (2000 populations)" in err and "one dense 2003 x 2003 operator" in err
    assert err.count("\n") == 1 and not out.exists()
    assert main([*argv, "--rates", "all"]) == 2  # every mode checked before any is run
    assert not out.exists()


@pytest.mark.parametrize(
    ("recovered", "m1", "m2"),
    [
        (2e-16, -7.2e-15, 3e-13),  # the probe's NY = 1 case: round-off "recovered" tracer, mean -36 s
        (0.0, 0.0, 0.0),
        (-1e-12, 1e-12, 1e-12),
        (0.5, -1.0, 1.0),  # a negative first moment
    ],
)
def test_residence_time_moments_are_never_negative(recovered, m1, m2):
    import math

    from coupling.metrics import residence_moments
    from pbm.simulate import rtd_moments

    moments = residence_moments(1.0, recovered, m1, m2)
    assert math.isnan(moments["mean_s"]) and math.isnan(moments["variance_s2"])
    assert not moments["recovered_fraction"] < 0
    # through the PBM's own function: amount 1, nothing held back beyond round-off
    out = rtd_moments(1.0, 1.0 - 2e-16, 0.5, 0.1, 100.0)
    assert math.isnan(out["mean_s"]) or out["mean_s"] >= 0
    good = residence_moments(2.0, 1.0, 10.0, 101.0 - 1e-12)  # variance 1 - 1e-12 round-off
    assert good["mean_s"] == 10.0 and good["variance_s2"] >= 0
