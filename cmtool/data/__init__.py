"""Map data: HD/SD map types, sources (procedural cities, real-map importers), scenes, rasters
and the dataset cache."""
