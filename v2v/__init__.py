"""v2v: multi-vehicle V2V collaborative relative-positioning simulator.

Pipeline (dependencies point one way)::

    traffic (libsumo) -> world/sensors -> exchange -> estimation -> metrics -> viz

Units are SI and angles radians inside the package; degrees appear only at the
input/output edge (scenario fields named ``*_deg``, printed tables).
"""

__version__ = "0.1.0"
