"""Traffic layer: the only code in v2v that imports libsumo (in :mod:`v2v.traffic.sumo`)."""
