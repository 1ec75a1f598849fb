"""Motion planning (DESIGN.md 5.1): AGV stations, arm rasters, tracker stations and the command sequence."""
