"""Cell configuration: pydantic models and the shipped TOML files."""

from tandemscan.config.loader import ConfigError, default_config_path, load_config
from tandemscan.config.models import CellConfig

__all__ = ["CellConfig", "ConfigError", "default_config_path", "load_config"]
