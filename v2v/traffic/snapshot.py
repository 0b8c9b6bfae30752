"""Typed per-vehicle truth snapshots returned by the traffic layer.

These types carry no libsumo objects, so every later stage (sensors, estimation,
metrics, viz) can use them without importing SUMO. All SUMO conventions stop at
:mod:`v2v.traffic.sumo`: positions here are the *antenna* (front-bumper position
plus the body-frame lever arm), ``azimuth_rad`` is radians clockwise from true north;
``grid_azimuth_rad`` and the background boxes' angle are radians clockwise from the net's +y
axis (SUMO's ``getAngle``: grid north; the two differ by the projection's grid convergence),
the angle that turns a body-frame vector into net XY.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True, kw_only=True)
class VehicleState:
    """Truth for one vehicle at one simulation step.

    Frames: see :mod:`v2v.frames`. ``xyz_m`` is the antenna phase centre in net XY
    plus height; ``ecef_m`` the same point in WGS-84 ECEF.
    """

    vehicle_id: str
    cluster: str
    is_lead: bool
    t_s: float
    xyz_m: NDArray[np.float64]  # antenna, net XY + height, (3,)
    lat_rad: float
    lon_rad: float
    h_m: float
    ecef_m: NDArray[np.float64]  # antenna, (3,)
    vel_enu_mps: NDArray[np.float64]  # (3,), true ENU at the antenna's position
    speed_mps: float
    accel_mps2: float  # longitudinal acceleration
    azimuth_rad: float  # heading, clockwise from true north, [0, 2pi)
    grid_azimuth_rad: float  # heading in net XY: clockwise from the net's +y axis (SUMO getAngle), [0, 2pi)
    yaw_rate_rps: float  # d(azimuth)/dt, positive clockwise (turning right)
    front_bumper_xy_m: NDArray[np.float64]  # SUMO getPosition, (2,)
    edge_id: str
    lane_id: str
    lane_index: int  # 0 = rightmost lane
    lane_width_m: float
    lateral_offset_m: float  # SUMO getLateralLanePosition: + to the left of the lane centre
    length_m: float
    width_m: float
    height_m: float


class EventKind(StrEnum):
    DEPARTED = "departed"
    ARRIVED = "arrived"
    TELEPORT = "teleport"
    COLLISION = "collision"
    LEFT_CLUSTER = "left_cluster"
    REJOINED_CLUSTER = "rejoined_cluster"
    LANE_CHANGE = "lane_change"


@dataclass(frozen=True, slots=True, kw_only=True)
class TrafficEvent:
    t_s: float
    kind: EventKind
    vehicle_id: str
    detail: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class TrafficStep:
    """All cluster vehicles present at one step, plus what happened during it.

    ``background`` holds boxes of non-cluster vehicles (for occlusion of radio links):
    rows of (x_m, y_m, grid azimuth (rad, clockwise from the net's +y axis), length_m, width_m,
    height_m), centre of the box.
    """

    t_s: float
    vehicles: dict[str, VehicleState]
    events: tuple[TrafficEvent, ...] = ()
    background: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 6)))
