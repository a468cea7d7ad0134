"""The validation campaign as data: a TOML file of typed changes beside the presets
(``workflows/presets/campaigns/<name>.toml``).

The file names the preset every run starts from and one ``[[change]]`` per run: its
``name``, its ``label`` in the report, and the values it sets, in the layout of a
configuration file (``[change.dem.operation]`` is the preset's ``[dem.operation]``), with
numbers as numbers. :func:`load_campaign` reads it into a :class:`Campaign` of
:class:`Change` objects and checks every run's configuration against the schema at once,
so that a bad key or value is one ConfigError naming the change, the key and what is
valid, before any run starts.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from workflows.config import PRESET_DIR, Config, config_from_dict, load_preset

#: Where the campaign files live, beside the presets.
CAMPAIGN_DIR = PRESET_DIR / "campaigns"
#: The campaign ``pbmdem validate`` runs.
VALIDATION_CAMPAIGN = "validation"
#: The keys of a ``[[change]]`` besides the configuration's sections.
CHANGE_KEYS = ("name", "label")
#: The configuration sections a change may set (a run's name is its change's).
CHANGE_SECTIONS = tuple(name for name in Config.model_fields if name != "name")


@dataclass(frozen=True)
class Change:
    """One run of a campaign: ``settings`` (nested like a configuration file, e.g.
    ``{"dem": {"operation": {"impeller_rpm": 150.0}}}``) applied to the campaign's preset."""

    name: str
    label: str
    settings: dict[str, Any]

    @property
    def assignments(self) -> tuple[tuple[str, Any], ...]:
        """The settings flattened to (dotted key, value) pairs, in the file's order."""
        return tuple(_flatten(self.settings))

    def apply(self, base: Config, source: str = "campaign") -> Config:
        """``base`` with this change's settings, validated as one configuration named
        ``<base name>-<change name>``; raises ConfigError naming the change and the key."""
        data = base.to_dict()
        _merge(data, self.settings, (), f"{source}, change {self.name!r}")
        config = config_from_dict(data, source=f"{source}, change {self.name!r}")
        return config.model_copy(update={"name": f"{base.name}-{self.name}"})


@dataclass(frozen=True)
class Campaign:
    """A campaign file: the ``preset`` every run starts from and its ``changes``, in order."""

    preset: str
    changes: tuple[Change, ...]
    source: str = "campaign"

    def labels(self) -> dict[str, str]:
        """Change name -> its label."""
        return {change.name: change.label for change in self.changes}

    def configs(self, base: Config | None = None) -> dict[str, Config]:
        """Each change's configuration (on ``base``, default the campaign's preset), every
        one validated before any is returned."""
        base = base if base is not None else load_preset(self.preset)
        return {change.name: change.apply(base, self.source) for change in self.changes}


def campaign_path(name: str = VALIDATION_CAMPAIGN) -> Path:
    """The file of the shipped campaign ``name``; ConfigError naming the valid ones."""
    names = sorted(p.name.removesuffix(".toml") for p in CAMPAIGN_DIR.iterdir() if p.name.endswith(".toml"))
    if name not in names:
        raise ConfigError(f"unknown campaign {name!r}; valid campaigns: {', '.join(names)}")
    return Path(str(CAMPAIGN_DIR / f"{name}.toml"))


def load_campaign(path: str | Path | None = None) -> Campaign:
    """The campaign in the TOML file ``path`` (default the shipped validation campaign),
    every run's configuration checked (:meth:`Campaign.configs`). Raises ConfigError."""
    path = Path(path) if path is not None else campaign_path()
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read campaign file {path}: {exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"campaign file {path} is not valid TOML: {exc}") from exc
    campaign = campaign_from_dict(data, str(path))
    campaign.configs()
    return campaign


def campaign_from_dict(data: dict[str, Any], source: str = "campaign") -> Campaign:
    """The :class:`Campaign` a parsed campaign file describes (its shape checked; the
    values are checked against the schema by :meth:`Campaign.configs`)."""
    unknown = sorted(set(data) - {"preset", "change"})
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown}; a campaign holds 'preset' and [[change]] tables")
    preset = data.get("preset")
    if not isinstance(preset, str):
        raise ConfigError(f"{source}: 'preset' = {preset!r}: the name of the preset every run starts from is needed")
    entries = data.get("change")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{source}: no [[change]] tables; a campaign needs one per run")
    changes = tuple(_change(entry, index, source) for index, entry in enumerate(entries))
    names = [change.name for change in changes]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ConfigError(f"{source}: change name(s) {repeated} appear more than once; each run needs its own")
    return Campaign(preset, changes, source)


def _change(entry: Any, index: int, source: str) -> Change:
    where = f"{source}, change {index + 1}"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: a [[change]] table is needed, got {entry!r}")
    for key in CHANGE_KEYS:
        if not isinstance(entry.get(key), str) or not entry[key]:
            raise ConfigError(f"{where}: '{key}' = {entry.get(key)!r}: text is needed")
    unknown = sorted(set(entry) - {*CHANGE_KEYS, *CHANGE_SECTIONS})
    if unknown:
        raise ConfigError(
            f"{where} ({entry['name']!r}): unknown key(s) {unknown}; a change holds {list(CHANGE_KEYS)} and "
            f"configuration sections {list(CHANGE_SECTIONS)}"
        )
    settings = {key: value for key, value in entry.items() if key in CHANGE_SECTIONS}
    return Change(entry["name"], entry["label"], settings)


def _merge(data: dict[str, Any], settings: dict[str, Any], path: tuple[str, ...], where: str) -> None:
    """Set ``settings``' values into the configuration dictionary ``data`` in place. A
    table set where the configuration holds a value is refused; unknown keys are left to
    the schema's check, which names them and the valid ones."""
    for key, value in settings.items():
        if isinstance(value, dict):
            node = data.setdefault(key, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{where}: '{'.'.join((*path, key))}' is a value, not a section")
            _merge(node, value, (*path, key), where)
        else:
            data[key] = value


def _flatten(settings: dict[str, Any], prefix: str = ""):
    for key, value in settings.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
