"""Sensors in real streets: short real-SUMO runs on the shipped nets, checked against geometry.

* ``open_highway``: its only buildings are sheds 5-7.5 m tall, all more than 100 m from the road
  (sumo_nets/README.md), so no building rises above atan((7.5 - 1.55) / 100) = 3.4 deg as seen
  from a 1.55 m roof antenna: below the 10 deg elevation mask. Every satellite above the mask
  must be tracked, all line of sight.
* ``urban_canyon``: streets ~27 m wall to wall between 27-118 m buildings: the skyline
  across a street is at >= atan((27 - 1.55) / 13.5) = 62 deg, so fewer satellites are tracked
  than on the highway, some only through a wall echo (NLOS), whose excess path is > 0
  (the echo travels farther than the blocked direct ray, MacGougan (2009) §3.5.1).
* UWB in the canyon with a truck inside the cluster: the link between the two cars on either
  side of a 3.8 m truck is blocked (antennas at 1.55 m); the radio then measures a wall
  reflection (MacGougan §2.8, §2.11.3), which is longer than the direct path: NLOS errors > 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from v2v.config.scenario import load_scenario
from v2v.run import run_scenario

NETS = Path(__file__).resolve().parents[1] / "sumo_nets"


def _gnss_run(tmp: Path, net: str) -> tuple[pd.DataFrame, dict]:
    sc = load_scenario(None, [f'network.name="{net}"', "duration_s=8", "seed=21", "clusters.0.vehicles=3",
                              "solutions=[]"])
    res = run_scenario(sc, tmp / net, quiet=True, replay=False, save_measurements=True)
    m = pd.read_parquet(tmp / net / "measurements.parquet")
    return m[m["type"] == "pseudorange"], res.summary


@pytest.fixture(scope="module")
def gnss_runs(tmp_path_factory) -> dict[str, tuple[pd.DataFrame, dict]]:
    tmp = tmp_path_factory.mktemp("city")
    return {net: _gnss_run(tmp, net) for net in ("open_highway", "urban_canyon")}


def _per_epoch(m: pd.DataFrame) -> pd.DataFrame:
    g = m.groupby([np.round(m["t_s"] * 1000).astype(int), "vehicle"])
    return pd.DataFrame({"tracked": g.size(), "los": g["los"].sum()})


@pytest.mark.sumo
def test_highway_tracks_every_satellite_above_the_mask_in_line_of_sight(gnss_runs):
    m, summary = gnss_runs["open_highway"]
    assert summary["gnss"]["nlos_fraction"] == 0.0
    assert m["los"].all(), "no building on the highway reaches the 10 deg mask"
    assert (m["err_nlos_m"] == 0.0).all()
    per = _per_epoch(m)
    # Same sky for all three vehicles (tens of metres apart) and nothing blocks it: the count
    # only changes when a satellite crosses the mask, which in 8 s happens at most once.
    assert per["tracked"].max() - per["tracked"].min() <= 1
    assert per["tracked"].min() >= 4


@pytest.mark.sumo
def test_canyon_tracks_fewer_satellites_and_its_nlos_errors_are_positive(gnss_runs):
    hw, _ = gnss_runs["open_highway"]
    cy, summary = gnss_runs["urban_canyon"]
    hw_per, cy_per = _per_epoch(hw), _per_epoch(cy)
    assert cy_per["tracked"].mean() < hw_per["tracked"].mean() - 1.0
    assert cy_per["los"].mean() < hw_per["los"].mean() - 2.0
    nlos = cy[~cy["los"]]
    assert len(nlos) > 0, "the canyon's deep streets must produce echo-only signals"
    assert 0.0 < summary["gnss"]["nlos_fraction"] < 1.0
    assert (nlos["err_nlos_m"] > 0.0).all(), "an echo is always longer than the blocked direct ray"
    # The echo of a wall at perpendicular distance d_w adds 2 d_w cos(el) cos(az - az_n) < 2 d_w:
    # walls within the 500 m search radius cannot add more than 1 km; the streets here give metres to tens.
    assert nlos["err_nlos_m"].median() > 1.0
    assert nlos["err_nlos_m"].max() < 1000.0
    # Echoes lose C/N0 (8 dB default echo loss) compared with direct signals.
    assert nlos["cn0_dbhz"].mean() < cy.loc[cy["los"], "cn0_dbhz"].mean()


@pytest.mark.sumo
def test_uwb_link_behind_a_truck_in_the_canyon_measures_a_longer_reflected_path():
    from v2v.pipeline import STREAM_UWB, build_uwb, child_seeds
    from v2v.run import resolve_network
    from v2v.traffic.sumo import NetFiles, SumoSimulation
    from v2v.world.buildings import load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    sc = load_scenario(None, ['network.name="urban_canyon"', "duration_s=12", "seed=4", "clusters.0.vehicles=3",
                              'clusters.0.vehicle_type=["passenger", "truck", "passenger"]', "clusters.0.lanes=[0]",
                              "solutions=[]"])
    net = resolve_network(sc)
    files = NetFiles(net_path=net.net_path, poly_paths=net.poly_paths, route_edges=net.route_edges)
    with SumoSimulation(sc, files, net.georef, seed=sc.seed) as sim:
        steps = [sim.snapshot()] + [sim.step() for _ in range(int(sc.duration_s / sc.step_length_s))]
        vehicles = sim.cluster_vehicle_ids()
    occl = OcclusionGeometry(load_polygons(list(net.poly_paths)))
    seeds = child_seeds(sc.seed)
    network = build_uwb(sc, vehicles, seeds[STREAM_UWB])
    r = network.simulate(steps, np.random.default_rng(seeds[STREAM_UWB].spawn(2)[1]), occlusion=occl)
    a, b = np.asarray(r.a), np.asarray(r.b)
    over_truck = (a == "c1.0") & (b == "c1.2")
    nlos = ~r.los
    assert nlos[over_truck].mean() > 0.5, "the truck sits between c1.0 and c1.2 in one lane"
    assert r.los[~over_truck].all(), "links to the truck itself pass nothing but air"
    assert (r.errors_m["nlos"][nlos] > 0.0).all(), "a reflected path is longer than the direct one"
    err = r.range_m - r.true_range_m
    # Total NLOS error = excess + (bias |.| < 0.5 m + scale ~0.5 % + noise 0.1 m): its median
    # is positive and larger than the LOS one.
    assert np.median(err[nlos]) > 0.5
    assert np.median(err[nlos]) > np.median(err[r.los]) + 0.3


@pytest.mark.parametrize("net", ["urban_canyon", "residential"])
def test_batched_sky_equals_per_antenna_sky_on_real_polygons(net):
    """``sky_many`` (one call per GNSS epoch) gives, ray by ray, what ``sky`` gives per antenna."""
    from v2v.world.buildings import load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    occl = OcclusionGeometry(load_polygons([NETS / net / f"{net}.poly.xml"]))
    rng = np.random.default_rng(3)
    ants = np.column_stack([rng.uniform(-200, 200, 12), rng.uniform(-200, 200, 12), np.full(12, 1.55)])
    az = rng.uniform(0, 2 * np.pi, (12, 9))
    el = np.radians(rng.uniform(5, 85, (12, 9)))
    many = occl.sky_many(ants, np.repeat(np.arange(12), 9), az.ravel(), el.ravel())
    assert many.blocked.any() and (~many.blocked).any()
    for i in range(12):
        one = occl.sky(ants[i], az[i], el[i])
        sl = slice(9 * i, 9 * (i + 1))
        np.testing.assert_array_equal(one.blocked, many.blocked[sl])
        np.testing.assert_array_equal(one.blocker_id, many.blocker_id[sl])
        np.testing.assert_allclose(one.echo_excess_m, many.echo_excess_m[sl], rtol=0, atol=1e-9)
        np.testing.assert_allclose(one.foliage_loss_db, many.foliage_loss_db[sl], rtol=0, atol=1e-12)
    if net == "residential":
        assert (many.foliage_loss_db > 0).any(), "street trees must attenuate some rays"
    else:
        assert np.isfinite(many.echo_excess_m).any(), "the canyon's walls must give some echoes"
