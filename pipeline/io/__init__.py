"""Cloud input and output: raw scans, PLY, E57 export."""
