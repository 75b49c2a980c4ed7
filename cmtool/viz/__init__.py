"""Pictures and Rerun recordings of maps, scenes and (later) models."""
