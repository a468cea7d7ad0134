"""Pipeline configuration: one TOML file with a ``[dem.*]`` part, a ``[pbm]`` part and the
``[steady_state]`` rule both sides are judged by.

Presets are ordinary TOML files in ``workflows/presets/``; copy one and edit it. Loading
validates every value before anything is written; errors name the key, the bad value and
what is allowed, and suggest the nearest valid key for a typo.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import json
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from coupling.errors import ConfigError
from coupling.metrics import SteadyStateRule
from dem.config import DemConfig
from pbm.config import PbmConfig

PRESET_DIR = resources.files("workflows") / "presets"


class Config(BaseModel):
    """The whole pipeline's configuration."""

    # allow_inf_nan=False also reaches the steady-state rule (a plain dataclass takes its
    # parent's config), so its inf/nan is refused by key like every other section's
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(
        "custom",
        pattern=r"^[A-Za-z0-9_.-]+$",
        description="name of the configuration (a preset's is its own); names the results directory "
        "NAME-HASH, the Slurm job and the report's preset",
    )
    dem: DemConfig = DemConfig()
    pbm: PbmConfig = PbmConfig()
    steady_state: SteadyStateRule = SteadyStateRule()

    @field_validator("steady_state", mode="before")
    @classmethod
    def _steady_numbers(cls, value: Any) -> Any:
        """The rule is a plain dataclass (shared with the PBM), validated in lax mode: its
        numbers get the strict check of the pydantic sections here (no boolean or text)."""
        if isinstance(value, dict):
            for key, item in value.items():
                if isinstance(item, (bool, str)):
                    raise ValueError(
                        f"steady_state.{key} = {_shown(item)} ({_type_name(item)}): {_TYPE_ERRORS['float_type']}"
                    )
        return value

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(mode="json")


def preset_names() -> list[str]:
    return sorted(p.name.removesuffix(".toml") for p in PRESET_DIR.iterdir() if p.name.endswith(".toml"))


def preset_path(name: str) -> Path:
    names = preset_names()
    if name not in names:
        hint = difflib.get_close_matches(name, names, n=1)
        raise ConfigError(
            f"unknown preset {name!r}; valid presets: {', '.join(names)}"
            + (f" (did you mean {hint[0]!r}?)" if hint else "")
        )
    return Path(str(PRESET_DIR / f"{name}.toml"))


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML configuration file."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"configuration path {path} is a directory; give a TOML file")
    if path.exists() and not path.is_file():
        raise ConfigError(
            f"configuration path {path} is not a regular file (a device, pipe or socket); give a TOML file"
        )
    if not path.is_file():
        raise ConfigError(f"configuration file {path} does not exist")
    try:
        # an editor's byte-order mark is no TOML: read past it
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path} is not a UTF-8 text file (undecodable byte at offset {exc.start}); "
            "a configuration is a TOML text file"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read configuration file {path}: {exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc
    if not data:
        # every key has a default, so an empty file would silently mean the paper-scale
        # run (2 mm particles, 1990 /s, 260 s: about a day of LIGGGHTS)
        raise ConfigError(
            f"{path} sets no keys (empty or only comments); start from a preset instead: "
            "`pbmdem config --preset reduced > my.toml`, then edit it "
            f"(presets: {', '.join(preset_names())})"
        )
    return config_from_dict(data, source=str(path))


def load_preset(name: str) -> Config:
    return load_config(preset_path(name))


def resolve_config(preset: str | None = None, config: str | Path | None = None) -> Config:
    """The CLI's rule: exactly one of a preset name or a config file."""
    if (preset is None) == (config is None):
        raise ConfigError("give exactly one of --preset NAME or --config FILE.toml")
    return load_preset(preset) if preset is not None else load_config(config)


def add_config_arguments(parser: argparse.ArgumentParser, required: bool = True) -> None:
    """The command-line face of :func:`resolve_config`: --preset NAME | --config FILE.toml."""
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument("--preset", help="preset name (see `pbmdem config --list`)")
    group.add_argument("--config", help="TOML configuration file")


def config_from_dict(data: dict[str, Any], source: str = "configuration") -> Config:
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_explain(exc, data, source)) from None


def override(config: Config, *assignments: str) -> Config:
    """``config`` with values replaced: each assignment is ``dotted.path=value`` (e.g.
    ``dem.geometry.inlet_margin_m=0.005``); the value is read as an int, a float, true /
    false / none, else text. All are applied before the result is validated like any
    configuration (ConfigError), so values that must change together can."""
    data = config.to_dict()
    for assignment in assignments:
        path, sep, text = assignment.partition("=")
        if not sep or not path:
            raise ConfigError(f"{assignment!r}: expected PATH=VALUE, e.g. dem.geometry.inlet_margin_m=0.005")
        value: Any = {"true": True, "false": False, "none": None}.get(text.lower(), text)
        for kind in (int, float):
            try:
                value = kind(text)
                break
            except ValueError:
                pass
        node = data
        *parents, leaf = path.split(".")
        for key in parents:
            if not isinstance(node.get(key), dict):
                raise ConfigError(f"{assignment!r}: no section '{key}' in the configuration")
            node = node[key]
        node[leaf] = value
    return config_from_dict(data, source=", ".join(assignments))


def config_without(config: Config, *paths: str) -> dict[str, Any]:
    """``config`` as a dictionary without its name and the values at the dotted ``paths``:
    what two runs must share to differ only in those values."""
    data = config.to_dict()
    data.pop("name", None)
    for path in paths:
        *parents, leaf = path.split(".")
        node = data
        for key in parents:
            node = node[key]
        node.pop(leaf, None)
    return data


#: what the runs of a feed library may differ in: the feed rate, and the duration (a slower
#: feed needs longer to fill and to pool an RTD)
FEED_LIBRARY_KEYS = ("dem.operation.feed_rate_total_per_s", "dem.operation.duration_s")


def same_but_feed(config: Config) -> dict[str, Any]:
    """What two runs of one feed library share: ``config`` less :data:`FEED_LIBRARY_KEYS`."""
    return config_without(config, *FEED_LIBRARY_KEYS)


#: what the runs of a speed library may differ in: the impeller speed (its value is read
#: from each run's operating point, :class:`coupling.operating.OperatingPoint`)
SPEED_LIBRARY_KEYS = ("dem.operation.impeller_rpm",)


def same_but_speed(config: Config) -> dict[str, Any]:
    """What two runs of one speed library share: ``config`` less :data:`SPEED_LIBRARY_KEYS`."""
    return config_without(config, *SPEED_LIBRARY_KEYS)


def dump_toml(config: Config) -> str:
    """TOML text of a resolved configuration (every value explicit), loadable by load_config."""
    data = config.to_dict()
    lines = [f"name = {json.dumps(data.pop('name'))}"]

    def emit(prefix: str, table: dict[str, Any]) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        if scalars:
            lines.append(f"\n[{prefix}]")
            for key, value in scalars.items():
                if value is not None:
                    lines.append(f"{key} = {_toml_value(value)}")
        for key, value in table.items():
            if isinstance(value, dict):
                emit(f"{prefix}.{key}", value)

    for key, value in data.items():
        emit(key, value)
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return json.dumps(str(value))


def _explain(exc: ValidationError, data: dict[str, Any], source: str) -> str:
    problems = []
    for err in exc.errors():
        loc = [str(part) for part in err["loc"]]
        key = ".".join(loc) or "(top level)"
        if err["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
            valid = _field_names(_model_at(Config, loc[:-1]))
            hint = difflib.get_close_matches(loc[-1], valid, n=1)
            home = _sections_with(loc[-1])
            problems.append(
                f"unknown key '{key}'"
                + (
                    f" (it belongs in {' or '.join(f'[{h}]' for h in home)})"
                    if home
                    else f" (did you mean '{hint[0]}'?)"
                    if hint
                    else ""
                )
                + (f"; valid keys here: {', '.join(valid)}" if valid else "")
            )
        elif err["type"] in _TYPE_ERRORS:
            value = err.get("input")
            problems.append(f"'{key}' = {_shown(value)} ({_type_name(value)}): {_TYPE_ERRORS[err['type']]}")
        else:
            msg = err["msg"].removeprefix("Value error, ")
            value = err.get("input")
            # a check across a section's fields names the fields in its message: the whole
            # section shown beside it would bury them
            shown = "" if isinstance(value, dict) else f" = {value!r}"
            problems.append(f"'{key}'{shown}: {msg}")
    if len(problems) == 1:  # one problem, one line (the CLI prints it as it is)
        return f"invalid {source}: {problems[0]}"
    return f"invalid {source}:\n  " + "\n  ".join(problems)


#: Strict-mode type errors (no coercion): what the key needs.
_TYPE_ERRORS = {
    "int_type": "an integer is needed (a whole number without a decimal point or exponent, not a boolean or text)",
    "float_type": "a number is needed (not a boolean or text)",
    "string_type": "text is needed (in quotes)",
    "bool_type": "true or false is needed",
    "list_type": "a list is needed",
}


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    return {int: "an integer", float: "a float", str: "text", list: "a list", dict: "a table"}.get(
        type(value), type(value).__name__
    )


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)


def _model_at(model: type, path: list[str]) -> type | None:
    for part in path:
        field = _fields(model).get(part)
        if field is None:
            return None
        model = field
    return model


def _fields(model: type | None) -> dict[str, type]:
    """Field name -> annotation of a pydantic model or a dataclass (the steady-state rule)."""
    if isinstance(model, type) and issubclass(model, BaseModel):
        return {name: f.annotation for name, f in model.model_fields.items()}
    if model is not None and dataclasses.is_dataclass(model):
        return {f.name: f.type for f in dataclasses.fields(model)}
    return {}


def _sections_with(name: str, model: type = Config, path: tuple[str, ...] = ()) -> list[str]:
    """The sections (dotted) of the configuration that have a key ``name``: where a key
    written under the wrong table belongs."""
    found = []
    for field, annotation in _fields(model).items():
        if _fields(annotation):
            found += _sections_with(name, annotation, (*path, field))
        elif field == name and path:
            found.append(".".join(path))
    return found


def _field_names(model: type | None) -> list[str]:
    return sorted(_fields(model))
