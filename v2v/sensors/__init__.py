"""v2v.sensors."""
