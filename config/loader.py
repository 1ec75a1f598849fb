"""Load and validate a cell configuration from TOML."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

from pydantic import ValidationError
from tandemscan.config.models import CellConfig

DEFAULT_CONFIG_NAME = "sim-cell.toml"


class ConfigError(Exception):
    """A configuration file is missing, unreadable or invalid; the message names the file, key and reason."""


def default_config_path() -> Path:
    """The shipped simulated-cell configuration."""
    return Path(str(resources.files("tandemscan.config").joinpath(DEFAULT_CONFIG_NAME)))


def load_config(path: Path | str | None = None) -> CellConfig:
    """Read ``path`` (default: the shipped sim cell) into a validated :class:`CellConfig`.

    Relative paths inside the file (part mesh, calibration file) are resolved against the
    file's folder, except for the shipped default whose paths are relative to the working directory.
    """
    path = Path(path) if path is not None else default_config_path()
    raw = read_toml(path)
    try:
        config = CellConfig.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(f"{path}: {format_validation_error(e)}") from e
    if path.resolve() != default_config_path().resolve():
        config = _resolve_relative_paths(config, path.parent)
    return config


def read_toml(path: Path, what: str = "file") -> dict:
    """The TOML document at ``path``; :class:`ConfigError` names the file (calling it ``what`` when missing)."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise ConfigError(f"{path}: {what} not found") from e
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from e
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from e


def format_validation_error(error: ValidationError) -> str:
    """One line per problem: ``key.path: reason``."""
    parts = []
    for item in error.errors():
        key = ".".join(str(p) for p in item["loc"]) or "(root)"
        parts.append(f"{key}: {item['msg']}")
    return "; ".join(parts)


def _resolve_relative_paths(config: CellConfig, base: Path) -> CellConfig:
    def fix(p: Path | None) -> Path | None:
        return p if p is None or p.is_absolute() else base / p

    part = config.part.model_copy(update={"mesh": fix(config.part.mesh)})
    job = config.job.model_copy(update={"calibration_file": fix(config.job.calibration_file)})
    phoxi = config.scanner.phoxi.model_copy(update={"producer_path": fix(config.scanner.phoxi.producer_path)})
    inspection = config.inspection.model_copy(update={"template": fix(config.inspection.template)})
    update = {"part": part, "job": job, "scanner": config.scanner.model_copy(update={"phoxi": phoxi}),
              "inspection": inspection}
    for role in ("measure_chassis", "tracking_chassis"):
        section = getattr(config, role)
        can = section.can.model_copy(update={"dbc": fix(section.can.dbc)})
        update[role] = section.model_copy(update={"can": can})
    return config.model_copy(update=update)
