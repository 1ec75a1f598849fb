"""A stage's parameters: a small frozen dataclass of what the stage uses, built once where the configuration is
read (the daemon, a command, a benchmark), as Open3D's ICP takes a convergence criteria object rather than a whole
configuration (docs/architecture.md, "Configuration and the stages").

The fields are keys of a configuration section of the same names (``[correction] icp_max_distance_mm`` is
``PairCriteria.icp_max_distance_mm``), so :meth:`FromSection.from_section` fills them from the section without
``pipeline/`` importing the configuration's models; the section validated every value and holds every default.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Self


class FromSection:
    """Mixin of a stage's frozen parameter dataclass whose fields are a configuration section's keys."""

    @classmethod
    def from_section(cls, section: object, **given: object) -> Self:
        """``cls`` with each field from ``given``, else from ``section``'s attribute of its name; a field whose
        type is itself a :class:`FromSection` (named bare in the annotation, imported by the class's module) is
        built from the same section."""
        names = vars(sys.modules[cls.__module__])
        values = {}
        for f in dataclasses.fields(cls):
            kind = names.get(f.type) if isinstance(f.type, str) else f.type
            if f.name in given:
                values[f.name] = given[f.name]
            elif isinstance(kind, type) and issubclass(kind, FromSection):
                values[f.name] = kind.from_section(section)
            else:
                values[f.name] = getattr(section, f.name)
        return cls(**values)
