"""Other tools' map formats: importers (Argoverse 2, Lanelet2, nuPlan, OpenStreetMap), exporters (Lanelet2,
OpenDRIVE, GeoJSON, OpenStreetMap) and SUMO's netconvert."""
