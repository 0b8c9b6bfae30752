"""v2v.sensors.gnss."""
