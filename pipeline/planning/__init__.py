"""Motion planning (docs/planning.md): AGV stations, arm rasters, tracker stations and the command sequence."""
