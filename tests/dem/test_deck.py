"""The LIGGGHTS deck: golden text per preset, Table 1 values, size classes, validation
before writing, the CLI, and acceptance by the real solver (marked ``liggghts``).

Regenerate the golden files deliberately with ``PBMDEM_REGEN_GOLDEN=1 python -m pytest
tests/dem/test_deck.py`` and review the diff.
"""

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from coupling.errors import ConfigError, DeckError, GeometryError
from dem.deck import (
    DECK_INFO,
    DUMP_GLOB,
    MAIN_DECK,
    MASSFLOW_FILES,
    MESH_FILES,
    RESUME_DECK,
    THERMO_COLUMNS,
    build_deck,
    deck_hash,
    deck_parameters,
    size_classes,
    write_deck,
)
from dem.liggghts import run_solver, solver_command, text_tail
from workflows.cli.main import main
from workflows.config import config_from_dict, load_preset

PRESETS = ["paper", "reduced", "smoke"]
GOLDEN = Path(__file__).parent / "golden"
REGEN = os.environ.get("PBMDEM_REGEN_GOLDEN") == "1"


@pytest.mark.parametrize("name", PRESETS)
def test_deck_matches_golden(name):
    files = build_deck(load_preset(name).dem)
    for fname in (MAIN_DECK, DECK_INFO):
        golden = GOLDEN / f"{name}.{fname}"
        if REGEN:
            golden.write_text(files[fname])
        assert golden.exists(), f"{golden} missing: run with PBMDEM_REGEN_GOLDEN=1"
        assert files[fname] == golden.read_text(), f"{fname} of preset {name} differs from {golden}"


def test_deck_is_deterministic_and_hash_tracks_content():
    dem = load_preset("smoke").dem
    a, b = build_deck(dem), build_deck(dem)
    assert a == b and deck_hash(a) == deck_hash(b)
    other = build_deck(dem.model_copy(update={"operation": dem.operation.model_copy(update={"impeller_rpm": 200.0})}))
    assert deck_hash(other) != deck_hash(a)
    assert set(a) == {MAIN_DECK, DECK_INFO, *MESH_FILES.values()}


def _fix_values(deck: str, name: str) -> list[float]:
    line = next(ln for ln in deck.splitlines() if f" {name} " in ln and ln.startswith("fix"))
    return [float(v) for v in line.split()[-9 if "peratomtypepair" in line else -3 :]]


def test_table_1_values():
    dem = load_preset("paper").dem
    deck = build_deck(dem)[MAIN_DECK]
    e_p, e_s = 2 * 2e6 * 1.33, 2 * 7.93e10 * 1.33
    np.testing.assert_allclose(_fix_values(deck, "youngsModulus"), [e_p, e_p, e_s], rtol=1e-6)
    np.testing.assert_allclose(_fix_values(deck, "poissonsRatio"), [0.33] * 3)
    np.testing.assert_allclose(_fix_values(deck, "coefficientRestitution"), [0.1] * 9)
    mu = np.array(_fix_values(deck, "coefficientFriction")).reshape(3, 3)
    assert mu[0, 0] == mu[0, 1] == mu[1, 1] == 0.5 and mu[0, 2] == mu[1, 2] == mu[2, 0] == 0.4
    np.testing.assert_allclose(_fix_values(deck, "coefficientRollingFriction"), [0.01] * 9)
    assert "hard_particles  yes" in deck
    assert "model hertz tangential history rolling_friction" in deck
    assert re.search(r"density constant 1500 ", deck)
    assert "move/mesh mesh impeller rotate origin 0. 0. 0. axis 1. 0. 0. period 0.24" in deck
    assert f"timestep        {dem.timestep_s:.10g}" in deck
    info = deck_parameters(dem)
    assert f"check/timestep/gran {info['thermo_every_steps']} " in deck
    assert f"thermo          {info['thermo_every_steps']}" in deck
    assert f"custom {info['dump_every_steps']} dumps/dump.*.txt id type x y z vx vy vz radius" in deck
    assert "reset_timestep" not in deck and "compress_tags yes" not in deck


def test_feed_rates_and_split():
    dem = load_preset("paper").dem
    deck = build_deck(dem)[MAIN_DECK]
    rates = dict(re.findall(r"fix ins([AB]) g\1 insert/rate/region .* particlerate (\S+)", deck))
    assert float(rates["A"]) == pytest.approx(995.0) and float(rates["B"]) == pytest.approx(995.0)
    assert "particletemplate/sphere" in deck and "atom_type 1" in deck and "atom_type 2" in deck
    uneven = dem.model_copy(update={"operation": dem.operation.model_copy(update={"feed_fraction_a": 0.25})})
    rates = dict(
        re.findall(r"fix ins([AB]) g\1 insert/rate/region .* particlerate (\S+)", build_deck(uneven)[MAIN_DECK])
    )
    assert float(rates["A"]) == pytest.approx(497.5) and float(rates["B"]) == pytest.approx(1492.5)


@pytest.mark.parametrize("n", range(1, 16))
def test_size_classes_match_mean_and_sd(n):
    d, w = size_classes(0.002, 0.0001, n)
    assert len(d) == n and w.sum() == pytest.approx(1.0)
    mean = np.sum(w * d)
    sd = np.sqrt(np.sum(w * (d - mean) ** 2))
    assert mean == pytest.approx(0.002, rel=1e-12)
    if n > 1:
        assert sd == pytest.approx(0.0001, rel=1e-9)
        assert d.min() >= 0.002 - 3 * 0.0001 - 1e-15 and d.max() <= 0.002 + 3 * 0.0001 + 1e-15


def test_one_template_when_sd_is_zero():
    d, w = size_classes(0.004, 0.0, 5)
    assert d.tolist() == [0.004] and w.tolist() == [1.0]
    data = {"dem": {"particles": {"diameter_sd_m": 0.0}}}
    deck = build_deck(config_from_dict(data).dem)[MAIN_DECK]
    assert deck.count("particletemplate/sphere") == 2  # one per component
    assert "numberbased 15486041 1 ptA0 1.00000000" in deck or re.search(r"numberbased \d+ 1 ptA0 1\.0+\n", deck)


@pytest.mark.parametrize("name", PRESETS)
def test_deck_text_size_distribution_matches_target(name):
    dem = load_preset(name).dem
    deck = build_deck(dem)[MAIN_DECK]
    radii = {
        m[0]: float(m[1])
        for m in re.findall(r"fix (ptA\d+) all particletemplate/sphere .* radius constant (\S+)", deck)
    }
    line = next(ln for ln in deck.splitlines() if "pddA all particledistribution" in ln).split()
    pairs = line[6:]
    d = np.array([2 * radii[pairs[i]] for i in range(0, len(pairs), 2)])
    w = np.array([float(pairs[i + 1]) for i in range(0, len(pairs), 2)])
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    mean = np.sum(w * d)
    assert mean == pytest.approx(dem.particles.diameter_m, rel=1e-6)
    assert np.sqrt(np.sum(w * (d - mean) ** 2)) == pytest.approx(dem.particles.diameter_sd_m, rel=1e-5)


def test_resume_deck_reads_restart_and_keeps_steps_continuous():
    dem = load_preset("smoke").dem
    files = build_deck(dem, resume_from="restart/restart.1000.bin")
    resume = files[RESUME_DECK]
    assert "read_restart    restart/restart.1000.bin" in resume
    assert "create_box" not in resume and "reset_timestep" not in resume
    end = deck_parameters(dem)["end_step"]
    assert resume.rstrip().endswith(f"run             {end} upto")
    for fix in ("insA", "insB", "outA", "outB", "rotor", "walls", "barrel", "ts"):
        assert f"fix {fix} " in resume
    assert "append discharge_A.txt" in resume and "file discharge_A.txt" in files[MAIN_DECK]
    with pytest.raises(DeckError, match="resume_from"):
        build_deck(dem, resume_from="a b.bin")


def test_thermo_header_is_the_documented_one():
    deck = build_deck(load_preset("smoke").dem)[MAIN_DECK]
    line = next(ln for ln in deck.splitlines() if ln.startswith("thermo_style"))
    assert [c.capitalize() if c in ("step", "atoms") else c[2:] for c in line.split()[2:]] == list(THERMO_COLUMNS)


def test_deck_without_dumps_differs_only_by_the_dump_command():
    dem = load_preset("smoke").dem
    with_dumps = build_deck(dem, resume_from="restart/restart.1000.bin")
    without = build_deck(dem, resume_from="restart/restart.1000.bin", dumps=False)
    for name in (MAIN_DECK, RESUME_DECK):
        kept = [line for line in with_dumps[name].splitlines() if not line.startswith("dump ")]
        assert without[name].splitlines() == kept and len(kept) == len(with_dumps[name].splitlines()) - 1
    assert {k: v for k, v in without.items() if k not in (MAIN_DECK, RESUME_DECK)} == {
        k: v for k, v in with_dumps.items() if k not in (MAIN_DECK, RESUME_DECK)
    }


@pytest.mark.parametrize(
    "data, error, fragment",
    [
        ({"dem": {"geometry": {"length_m": 0}}}, ConfigError, "'dem.geometry.length_m' = 0"),
        ({"dem": {"geometry": {"shaft_radius_m": -0.01}}}, ConfigError, "shaft_radius_m"),
        ({"dem": {"particles": {"diameter_m": 0}}}, ConfigError, "diameter_m"),
        ({"dem": {"geometry": {"blade_tip_clearance_m": 0.002}}}, ConfigError, "pinched"),
        ({"dem": {"operation": {"impeller_rpm": 0}}}, ConfigError, "impeller_rpm"),
        ({"dem": {"operation": {"impeller_rpm": -10}}}, ConfigError, "impeller_rpm"),
        ({"dem": {"operation": {"feed_rate_total_per_s": 0}}}, ConfigError, "feed_rate_total_per_s"),
        ({"dem": {"numerics": {"timestep_rayleigh_fraction": 0.3}}}, ConfigError, "stable limit"),
        ({"dem": {"geometry": {"weir_heigth_m": 0.02}}}, ConfigError, "did you mean 'weir_height_m'"),
        ({"dem": {"geometry": {"feed_x_max_m": 0.05}}}, GeometryError, "intersects the volume swept"),
        ({"dem": {"geometry": {"weir_height_m": 0.045}}}, GeometryError, "weir_height_m = 0.045"),
    ],
)
def test_invalid_parameters_refused_before_any_file(tmp_path, data, error, fragment):
    with pytest.raises(error) as info:
        files = build_deck(config_from_dict(data).dem)
        write_deck(files, tmp_path / "run")
    assert fragment in str(info.value)
    assert not (tmp_path / "run").exists()


def test_cli_writes_deck_and_refuses_bad_input(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["dem", "deck", "--preset", "smoke", "--out", str(out), "--view-stl", "--png"]) == 0
    assert (out / "meshes" / "view_barrel.stl").is_file() and (out / "geometry.png").stat().st_size > 1000
    for name in (MAIN_DECK, DECK_INFO, "config.toml", *MESH_FILES.values()):
        assert (out / name).is_file(), name
    assert (out / "dumps").is_dir() and (out / "restart").is_dir()
    files = build_deck(load_preset("smoke").dem)
    assert (out / "config.toml").read_text().startswith(f"# deck_hash = {deck_hash(files)}\n")
    info = json.loads((out / DECK_INFO).read_text())
    assert info["thermo_columns"] == list(THERMO_COLUMNS) and info["dump_glob"] == DUMP_GLOB
    # the resolved config reloads to the same configuration
    from workflows.config import load_config

    assert load_config(out / "config.toml") == load_preset("smoke")
    capsys.readouterr()
    assert main(["dem", "deck", "--preset", "smok", "--out", str(tmp_path / "x")]) == 2
    assert "unknown preset 'smok'" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[dem.geometry]\nfeed_x_max_m = 0.05\n")
    assert main(["dem", "deck", "--config", str(bad), "--out", str(tmp_path / "y")]) == 2
    assert "swept" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


@pytest.mark.parametrize(
    "section, key, value, fragment",
    [
        ("operation", "duration_s", 1e300, "operation.duration_s = 1e+300 s is 1.696e+304 steps of 5.895e-05 s"),
        ("operation", "duration_s", 2e5, "operation.duration_s = 200000 s is 3.393e+09 steps"),
        ("numerics", "restart_interval_s", 1e9, "numerics.restart_interval_s = 1e+09 s is"),
    ],
)
@pytest.mark.parametrize("command", ["deck", "slurm", "run"])
def test_every_command_that_writes_a_deck_refuses_steps_liggghts_rejects(
    tmp_path, capsys, command, section, key, value, fragment
):
    """One validation (dem.deck.deck_parameters, under build_deck) for every command that
    writes a deck: ``dem deck`` wrote ``run 1696...(300 digits) upto`` with exit 0 where
    ``dem run`` and ``dem slurm`` refused (issue 46); now each refuses in the same line,
    before any directory exists."""
    from workflows.config import dump_toml

    smoke = load_preset("smoke")
    section_model = getattr(smoke.dem, section).model_copy(update={key: value})
    config = tmp_path / "long.toml"
    config.write_text(
        dump_toml(smoke.model_copy(update={"dem": smoke.dem.model_copy(update={section: section_model})}))
    )
    out = tmp_path / "out"
    where = ["--runs-dir", str(out)] if command == "run" else ["--out", str(out)]
    assert main(["dem", command, "--config", str(config), *where]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pbmdem: error: {fragment}") and err.count("\n") == 1
    assert f"LIGGGHTS takes at most {2**31 - 1} steps" in err
    assert not out.exists()


def test_the_longest_run_liggghts_takes_is_written():
    config = load_preset("smoke").dem
    dt = config.timestep_s
    longest = config.model_copy(
        update={"operation": config.operation.model_copy(update={"duration_s": (2**31 - 1) * dt})}
    )
    assert deck_parameters(longest)["end_step"] == 2**31 - 1
    longer = config.model_copy(update={"operation": config.operation.model_copy(update={"duration_s": 2**31 * dt})})
    with pytest.raises(DeckError, match="is 2.147e\\+09 steps"):
        deck_parameters(longer)


def _run_liggghts(run_dir: Path, deck: str, np_: int = 1, timeout: float = 240, log: str = "log.liggghts") -> str:
    """The solver's output; a missing solver raises SolverNotFoundError: these tests are never skipped."""
    command = [*solver_command(load_preset("smoke").dem.run, np_, deck), "-log", log]
    result = run_solver(command, run_dir, f"{log}.out", timeout_s=timeout)
    assert result.failure is None, text_tail(result.output_file, 60)
    return result.output


def _short(files: dict[str, str], steps: int) -> dict[str, str]:
    deck = files[MAIN_DECK]
    assert len(re.findall(r"^run .*$", deck, flags=re.M)) == 1
    return {**files, MAIN_DECK: re.sub(r"^run .*$", f"run             {steps}", deck, flags=re.M)}


@pytest.mark.liggghts
@pytest.mark.parametrize("name", PRESETS)
def test_liggghts_accepts_every_preset_deck(tmp_path, name):
    dem = load_preset(name).dem
    files = _short(build_deck(dem), 200)
    write_deck(files, tmp_path)
    out = _run_liggghts(tmp_path, MAIN_DECK)
    header = next(ln for ln in out.splitlines() if ln.split()[:1] == ["Step"])
    assert header.split() == list(THERMO_COLUMNS)
    assert "whitelist" not in out  # the contact model runs the optimised code path
    assert (tmp_path / "dumps" / "dump.0.txt").exists()
    assert "Loop time" in out


@pytest.mark.liggghts
@pytest.mark.slow
def test_liggghts_smoke_inserts_and_restart_resumes(tmp_path):
    """A short smoke run: particles inserted at the configured rate, a restart written, and
    the resume deck continues from it with continuous steps."""
    dem = load_preset("smoke").dem
    dem = dem.model_copy(
        update={
            "operation": dem.operation.model_copy(update={"duration_s": 1.0}),
            "numerics": dem.numerics.model_copy(update={"restart_interval_s": 0.5}),
        }
    )
    info = deck_parameters(dem)
    restart_step = info["restart_every_steps"]
    files = build_deck(dem, resume_from=f"restart/restart.{restart_step}.bin")
    write_deck(files, tmp_path)
    out = _run_liggghts(tmp_path, MAIN_DECK)
    rows = [
        ln.split() for ln in out.splitlines() if re.match(r"^\s+\d+\s", ln) and len(ln.split()) == len(THERMO_COLUMNS)
    ]
    last = dict(zip(THERMO_COLUMNS, map(float, rows[-1])))
    expected = dem.operation.feed_rate_total_per_s * 1.0
    inserted = last["insA"] + last["insB"]
    assert abs(inserted - expected) <= 0.15 * expected + 4
    assert (tmp_path / f"restart/restart.{restart_step}.bin").exists()
    out2 = _run_liggghts(tmp_path, RESUME_DECK, log="log.resume.liggghts")
    rows2 = [
        ln.split() for ln in out2.splitlines() if re.match(r"^\s+\d+\s", ln) and len(ln.split()) == len(THERMO_COLUMNS)
    ]
    assert int(rows2[0][0]) == restart_step and int(rows2[-1][0]) == info["end_step"]
    assert float(rows2[-1][1]) == pytest.approx(1.0, abs=2 * info["timestep_s"])
    for fname in MASSFLOW_FILES.values():
        assert list(tmp_path.glob(fname + "*")), fname
    assert (tmp_path / "log.liggghts").read_text().count("Loop time") == 1
    assert (tmp_path / "log.resume.liggghts").is_file()
