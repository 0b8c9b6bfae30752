"""The traffic layer drives the real libsumo on a tiny net (tests/data/tiny: 600 m straight
two-lane road east, a curve, then north)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from v2v.config.scenario import load_scenario
from v2v.errors import UserError
from v2v.frames import GeoReference, wrap_angle
from v2v.traffic.sumo import NetFiles, SumoSimulation

pytestmark = pytest.mark.sumo
TINY = Path(__file__).parent / "data" / "tiny"
PROJ = "+proj=tmerc +lat_0=51.0775 +lon_0=-114.1295 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"


@pytest.fixture(scope="module")
def tiny_net(tmp_path_factory) -> Path:
    import sumo

    out = tmp_path_factory.mktemp("tiny") / "tiny.net.xml"
    subprocess.run(
        [str(Path(sumo.SUMO_HOME) / "bin" / "netconvert"), "--node-files", str(TINY / "tiny.nod.xml"),
         "--edge-files", str(TINY / "tiny.edg.xml"), "-o", str(out), "--seed", "1"],
        check=True, capture_output=True,
    )
    return out


def _drive(net: Path, overrides: list[str], n_steps: int, seed: int = 7, proj: str = PROJ):
    sc = load_scenario(overrides=overrides)
    files = NetFiles(net_path=net, route_edges=("AB", "BC", "CD"))
    with SumoSimulation(sc, files, GeoReference(proj=proj), seed=seed) as sim:
        steps = [sim.snapshot()] + [sim.step() for _ in range(n_steps)]
        import libsumo

        lanes = {lid: np.asarray(libsumo.lane.getShape(lid)) for lid in libsumo.lane.getIDList()}
        geo_check = [(x, y, libsumo.simulation.convertGeo(x, y)) for x, y in [(0.0, 0.0), (650.0, 30.0), (800.0, 400.0)]]
    return sc, steps, lanes, geo_check


def _dist_to_polyline(p: np.ndarray, line: np.ndarray) -> float:
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def test_cluster_drives_on_the_road_with_consistent_azimuth(tiny_net):
    sc, steps, lanes, _ = _drive(tiny_net, ["clusters.0.vehicles=3", "clusters.0.lanes=[0,1]"], 600)
    ids = {"c1.0", "c1.1", "c1.2"}
    assert set(steps[0].vehicles) == ids, "all cluster vehicles are on the road at t_s = 0"
    assert steps[0].t_s == 0.0
    lead = [v for v in steps[0].vehicles.values() if v.is_lead]
    assert [v.vehicle_id for v in lead] == ["c1.0"]
    arm = np.array(sc.vehicle_types["passenger"].antenna_lever_arm_m)
    max_front_dist = 0.0
    for st in steps:
        for v in st.vehicles.values():
            # The front-bumper centre lies on its lane's centre line (SUMO's definition) ...
            d_front = _dist_to_polyline(v.front_bumper_xy_m, lanes[v.lane_id]) if v.lane_id in lanes else 0.0
            max_front_dist = max(max_front_dist, d_front)
            # ... and the antenna is the body-frame lever arm away from it, turned by the grid
            # azimuth (SUMO's angle); the true azimuth is that plus the grid convergence there
            a = v.grid_azimuth_rad
            gamma = GeoReference(proj=PROJ).grid_convergence_rad(*v.xyz_m[:2].tolist())
            assert abs(math.remainder(v.azimuth_rad - a - gamma, 2 * math.pi)) < 1e-6
            fwd = np.array([math.sin(a), math.cos(a)])
            left = np.array([-math.cos(a), math.sin(a)])
            np.testing.assert_allclose(v.xyz_m[:2], v.front_bumper_xy_m + arm[0] * fwd + arm[1] * left, atol=0.01)
            assert v.xyz_m[2] == pytest.approx(arm[2])
    # SUMO's continuous lane change moves a vehicle up to one lane width (3.2 m) across
    # while it is still on its old lane; outside that, the distance is ~0.
    assert max_front_dist < 3.3
    # Azimuth vs direction of travel on the straight edge (finite differences of position, 2 deg).
    for vid in ids:
        xy = np.array([st.vehicles[vid].xyz_m[:2] for st in steps if st.vehicles[vid].edge_id == "AB"])
        az = np.array([st.vehicles[vid].azimuth_rad for st in steps if st.vehicles[vid].edge_id == "AB"])
        d = np.diff(xy, axis=0)
        moving = np.linalg.norm(d, axis=1) > 0.5
        fd_az = np.arctan2(d[:, 0], d[:, 1])
        err = np.abs(wrap_angle(fd_az - az[1:]))[moving]
        assert len(err) > 100 and np.degrees(err.max()) < 2.0
        # and the ENU velocity agrees with the position change (speed along azimuth).
        v = np.array([st.vehicles[vid].vel_enu_mps[:2] for st in steps if st.vehicles[vid].edge_id == "AB"])
        np.testing.assert_allclose(np.degrees(np.arctan2(v[1:][moving, 0], v[1:][moving, 1])), 90.0, atol=2.0)


def test_grid_and_true_azimuth_off_the_central_meridian(tiny_net):
    """The same net 200 km east of its projection's central meridian (false easting -200 km, as
    a UTM zone's edge): SUMO's angle is the grid azimuth, which turns the lever arm in net XY;
    the true azimuth adds the grid convergence, gamma = atan(tan(dlon) sin(lat)) on the sphere
    (dlon = 200 km / (R cos lat): 0.0384 rad at 51.08 N; the ellipsoid's differs by < 1 %)."""
    proj = PROJ.replace("+x_0=0", "+x_0=-200000")
    sc, steps, _, _ = _drive(tiny_net, ["clusters.0.vehicles=2"], 150, proj=proj)
    arm = np.array(sc.vehicle_types["passenger"].antenna_lever_arm_m)
    lat = math.radians(51.0775)
    gamma_hand = math.atan(math.tan(200e3 / (6371e3 * math.cos(lat))) * math.sin(lat))
    n = 0
    for st in steps:
        for v in st.vehicles.values():
            a = v.grid_azimuth_rad
            fwd, left = np.array([math.sin(a), math.cos(a)]), np.array([-math.cos(a), math.sin(a)])
            np.testing.assert_allclose(v.xyz_m[:2], v.front_bumper_xy_m + arm[0] * fwd + arm[1] * left, atol=1e-6)
            gamma = math.remainder(v.azimuth_rad - a, 2 * math.pi)
            assert gamma == pytest.approx(gamma_hand, rel=0.01)
            n += 1
    assert n > 200


def test_headway_follows_the_two_second_rule(tiny_net):
    _, steps, _, _ = _drive(tiny_net, ["clusters.0.vehicles=3", "clusters.0.lanes=[0]"], 300)
    st = steps[-1]
    gaps = [st.vehicles["c1.0"].xyz_m[0] - st.vehicles["c1.1"].xyz_m[0], st.vehicles["c1.1"].xyz_m[0] - st.vehicles["c1.2"].xyz_m[0]]
    speed = st.vehicles["c1.0"].speed_mps
    # 2 s at ~13.9 m/s = 27.8 m; Krauss driver imperfection (sigma 0.5) varies it by a few metres.
    for g in gaps:
        assert 2.0 * speed - 6.0 < g < 2.0 * speed + 6.0


def test_same_seed_same_trajectories(tiny_net):
    a = _drive(tiny_net, ["clusters.0.vehicles=4", "clusters.0.lanes=[0,1]"], 200, seed=11)[1]
    b = _drive(tiny_net, ["clusters.0.vehicles=4", "clusters.0.lanes=[0,1]"], 200, seed=11)[1]
    for sa, sb in zip(a, b, strict=True):
        for vid in sa.vehicles:
            assert np.array_equal(sa.vehicles[vid].ecef_m, sb.vehicles[vid].ecef_m)


def test_georeference_agrees_with_sumo_convert_geo(tiny_net):
    _, _, _, checks = _drive(tiny_net, ["clusters.0.vehicles=2"], 1)
    g = GeoReference(proj=PROJ)
    for x, y, (lon_deg, lat_deg) in checks:  # convertGeo returns (lon, lat)
        lat, lon = g.xy_to_geodetic(x, y)
        assert np.degrees(lat) == pytest.approx(lat_deg, abs=1e-9)
        assert np.degrees(lon) == pytest.approx(lon_deg, abs=1e-9)


def test_route_not_connected_is_a_user_error(tiny_net):
    sc = load_scenario(overrides=["clusters.0.vehicles=2"])
    with pytest.raises(UserError, match="network.route_edges"):
        with SumoSimulation(sc, NetFiles(net_path=tiny_net, route_edges=("AB", "CD")), GeoReference(proj=PROJ), seed=1):
            pass


def test_arrivals_are_events_not_crashes(tiny_net):
    sc = load_scenario(overrides=["clusters.0.vehicles=2"])
    files = NetFiles(net_path=tiny_net, route_edges=("AB", "BC", "CD"))
    arrived = []
    with SumoSimulation(sc, files, GeoReference(proj=PROJ), seed=3) as sim:
        for _ in range(1500):  # 150 s: the ~1.1 km route takes ~80 s at 13.9 m/s
            st = sim.step()
            arrived += [e.vehicle_id for e in st.events if e.kind.value == "arrived"]
            if not st.vehicles:
                break
    assert sorted(arrived) == ["c1.0", "c1.1"]


def _drive_raw(net: Path, overrides: list[str], n_steps: int, batches: list[int], seed: int = 7):
    """As :func:`_drive`, the steps read raw (``step_raw``) and converted in runs of ``batches``."""
    sc = load_scenario(overrides=overrides)
    files = NetFiles(net_path=net, route_edges=("AB", "BC", "CD"))
    with SumoSimulation(sc, files, GeoReference(proj=PROJ), seed=seed) as sim:
        raws = [sim.raw_snapshot()] + [sim.step_raw() for _ in range(n_steps)]
        steps, a = [], 0
        for b in [*batches, len(raws)]:
            steps += sim.convert(raws[a:b])
            a = b
    return steps


def test_steps_converted_together_equal_one_at_a_time(tiny_net):
    """SumoSimulation.convert of many raw steps at once (what v2v.run does, a chunk at a time)
    gives every step's truth, events and background exactly as one step at a time: the frame
    conversions are element for element, the yaw rate, lane and membership state carried from
    step to step (a 40 m cluster limit makes the last vehicles leave: membership events)."""
    ov = ["clusters.0.vehicles=4", "clusters.0.lanes=[0,1]", "clusters.0.max_separation_m=40.0"]
    one = _drive(tiny_net, ov, 400, seed=5)[1]
    together = _drive_raw(tiny_net, ov, 400, [1, 38, 200, 201], seed=5)
    assert len(one) == len(together) == 401
    assert {e.kind.value for st in one for e in st.events} >= {"left_cluster", "rejoined_cluster"}
    for sa, sb in zip(one, together, strict=True):
        assert sa.t_s == sb.t_s and sa.events == sb.events and np.array_equal(sa.background, sb.background)
        assert list(sa.vehicles) == list(sb.vehicles)
        for vid, va in sa.vehicles.items():
            vb = sb.vehicles[vid]
            for f in dataclasses.fields(va):
                x, y = getattr(va, f.name), getattr(vb, f.name)
                assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, (sa.t_s, vid, f.name, x, y)
