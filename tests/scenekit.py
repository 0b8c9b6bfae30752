"""A shared hand-built urban scene for the sensor tests (tests/test_bearing.py, tests/test_uwb.py):
a street crossing where buildings, cars and a background truck block links, used to check that the
batched occlusion query of a chunk equals the per-step path."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from v2v.traffic.snapshot import TrafficStep
from v2v.world.buildings import Building, World
from v2v.world.occlusion import OcclusionGeometry


def crossing_scene(make_steps: Callable[..., list[TrafficStep]]) -> tuple[list[TrafficStep], OcclusionGeometry]:
    """A street crossing in a hand-built city, 20 s at 10 Hz, antennas 1.0 m up (below
    the 1.5 m car roofs, so cars block too).

    Four corner blocks (10-25 m tall) leave 16 m wide streets along both axes. ``a`` and ``c``
    (12 m behind) drive east at 4 m/s on y = -2, ``b`` and ``d`` (10 m behind) north at 3 m/s on
    x = 2: the corner block cuts a/c-b/d links early on, the crossing clears them later. ``c``
    leaves for 8 s <= t < 11 s (the vehicle set changes: separate runs and box sets), and a 6 m
    truck (3.5 m tall, non-cluster ``background`` box) drives between ``a`` and ``c`` for t < 12 s.
    A probe that each query sees its own step's boxes: a 4 m van between ``b`` and ``d`` at every
    other step. ``make_steps(t_s, xy_by_vehicle, z_m=...)``: the test file's truth builder.
    """
    def block(bid: str, x0: float, x1: float, y0: float, y1: float, h: float) -> Building:
        fp = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        return Building(id=bid, footprint_xy_m=fp, height_m=h, height_source="height")

    occ = OcclusionGeometry(World(buildings=(
        block("NE", 8, 60, 8, 60, 20.0), block("NW", -60, -8, 8, 60, 15.0),
        block("SW", -60, -8, -60, -8, 25.0), block("SE", 8, 60, -60, -8, 10.0),
    )))
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([-50 + 4 * t, z - 2], 1), "c": np.stack([-62 + 4 * t, z - 2], 1),
          "b": np.stack([z + 2, -50 + 3 * t], 1), "d": np.stack([z + 2, -60 + 3 * t], 1)}
    steps = []
    for st in make_steps(t, xy, z_m=1.0):
        veh = {k: v for k, v in st.vehicles.items() if not (k == "c" and 8.0 <= st.t_s < 11.0)}
        bg = [[-56 + 4 * st.t_s, -2.0, math.pi / 2, 6.0, 2.5, 3.5]] if st.t_s < 12.0 else []
        if len(steps) % 2 == 0:
            bg.append([2.0, -55 + 3 * st.t_s, 0.0, 4.0, 2.5, 3.5])
        steps.append(TrafficStep(t_s=st.t_s, vehicles=veh, background=np.array(bg).reshape(-1, 6)))
    return steps, occ


class LinksOnly:
    """The occlusion interface without ``links_many``: the sensors then ask ``links`` step by step."""

    def __init__(self, geometry):
        self.geometry = geometry

    def links(self, p0, p1, boxes, exclude):
        return self.geometry.links(p0, p1, boxes, exclude)
