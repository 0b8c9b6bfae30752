"""Chunked (streaming) runs: issue 8, "a 1-hour, 10-vehicle run keeps memory flat".

``run_scenario`` processes a run in chunks of simulated time; every random stream, sensor
state, message in flight and filter continues across chunks. Two properties follow from the
design and are checked here:

* Invariance: the outputs do not depend on the chunk length. A physical simulation must not
  change with how the computer slices its time axis; the check is exact (bit-identical),
  because the draws, sends, deliveries and filter updates happen in the same order whatever
  the slicing, and floating point is deterministic for the same operations in the same order.
* Memory is O(1) in run length: the Python heap while streaming (tracemalloc, sampled each
  time a filter finishes a chunk) of a 240 s run exceeds a 120 s run's by less than a small
  bound (see ``test_memory_does_not_grow_with_duration``).
"""

from __future__ import annotations

import json
import math
import tracemalloc

import numpy as np
import pandas as pd
import pytest

from v2v.config.scenario import load_scenario
from v2v.run import run_scenario

pytestmark = pytest.mark.sumo

ONE = ['solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]']
VOLATILE = {"wall_s", "real_time_factor", "timing_s"}


def _same_frames(a: pd.DataFrame, b: pd.DataFrame) -> None:
    assert list(a.columns) == list(b.columns)
    assert list(a.dtypes) == list(b.dtypes)
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_chunked_equals_one_chunk(tmp_path):
    """7 s chunks vs the whole run as one chunk: identical epochs, truth and summary.

    Two solutions (one with azimuth states) and a V2V latency that carries messages across
    chunk boundaries (100 ms at 10 Hz GNSS: every chunk ends with messages in flight)."""
    over = [
        "duration_s=22.0", "exchange.latency_s=0.1",
        'solutions=[{name="GPS", sensors=["gnss"]}, '
        '{name="GPS+UWB+Bearing az-est", sensors=["gnss","uwb","bearing"], azimuth="estimated"}]',
    ]
    outs = {}
    for chunk in (7.0, math.inf):
        out = tmp_path / f"c{chunk}"
        run_scenario(load_scenario(None, over), out, quiet=True, replay=False, chunk_s=chunk)
        outs[chunk] = out
    a, b = outs[7.0], outs[math.inf]
    for name in ("epochs.parquet", "truth.parquet"):
        _same_frames(pd.read_parquet(a / name), pd.read_parquet(b / name))
    sa = json.loads((a / "summary.json").read_text())
    sb = json.loads((b / "summary.json").read_text())
    for k in set(sa) | set(sb):
        if k not in VOLATILE:
            assert sa.get(k) == sb.get(k), k
    assert sa["uwb"]["ranges"] > 0 and sa["bearing"]["measurements"] > 0 and sa["exchange"]["sent"] > 0


def test_uwb_stream_equals_one_call():
    """UwbStream fed in uneven chunks equals one UwbNetwork.simulate call, bit for bit
    (same per-pair draws in the same order, multipath Gauss-Markov carried across chunks)."""
    from v2v.sensors.uwb import UwbNetwork, concat_ranges
    from v2v.traffic.snapshot import TrafficStep, VehicleState

    t = np.round(np.arange(0.0, 40.0 + 1e-9, 0.1), 6)

    def state(vid: str, k: int, x0: float) -> VehicleState:
        x = x0 + 12.0 * t[k]
        return VehicleState(vehicle_id=vid, t_s=float(t[k]), cluster="c", is_lead=vid == "a", xyz_m=np.array([x, 0.0, 1.5]),
                            lat_rad=0.9, lon_rad=0.2, h_m=1.5, ecef_m=np.array([4.0e6 + x, 1.0e6, 4.8e6]),
                            vel_enu_mps=np.array([12.0, 0.0, 0.0]), speed_mps=12.0, accel_mps2=0.0,
                            azimuth_rad=math.pi / 2, grid_azimuth_rad=math.pi / 2, yaw_rate_rps=0.0, front_bumper_xy_m=np.array([x, 0.0]),
                            edge_id="e", lane_id="e_0", lane_index=0, lane_width_m=3.2, lateral_offset_m=0.0,
                            length_m=4.5, width_m=1.8, height_m=1.5)

    steps = [TrafficStep(t_s=float(t[k]), vehicles={v: state(v, k, x0) for v, x0 in (("a", 0.0), ("b", -30.0), ("c", -60.0))})
             for k in range(t.size)]

    def net() -> UwbNetwork:
        return UwbNetwork(vehicle_ids=["a", "b", "c"], rng=np.random.default_rng(3), profile="mssi")

    whole = net().simulate(steps, np.random.default_rng(4))
    st = net().stream(np.random.default_rng(4), t_start_s=steps[0].t_s, t_end_s=steps[-1].t_s)
    parts, i = [], 0
    for n in (1, 37, 5, 120, 3, 200):
        parts.append(st.push(steps[i:i + n]))
        i += n
    parts.append(st.push(steps[i:]))
    parts.append(st.finish())
    chunked = concat_ranges(parts)
    assert whole.n > 300  # 3 pairs x ~3 Hz x 40 s, minus losses
    assert chunked.a == whole.a and chunked.b == whole.b
    for f in ("t_s", "true_t_s", "range_m", "true_range_m", "los"):
        assert np.array_equal(getattr(chunked, f), getattr(whole, f)), f
    for k, v in whole.errors_m.items():
        assert np.array_equal(chunked.errors_m[k], v), k


def test_uwb_generator_copy_continues_the_stream():
    """The UWB synthesis's generator copies (``_Clone.of``) continue the source's stream
    exactly: after a 32-bit draw (numpy buffers the other half of its 64-bit output: the copy
    must carry it), and advanced by ``k`` 64-bit outputs (= ``k`` uniform doubles, one output
    each), whatever seed the copy's bit generator was made with."""
    from v2v.sensors.uwb import _Clone

    g = np.random.default_rng(11)
    g.integers(0, 2**32, size=3, dtype=np.uint32)  # odd count: a buffered half is pending
    copy = _Clone.of(g)
    assert np.array_equal(copy.integers(0, 2**32, size=5, dtype=np.uint32), g.integers(0, 2**32, size=5, dtype=np.uint32))
    assert np.array_equal(copy.standard_normal(64), g.standard_normal(64))
    ahead = _Clone.of(g, 10)
    g.random(10)
    assert np.array_equal(ahead.random(32), g.random(32))


def _streaming_heap_mb(tmp_path, duration_s: float, monkeypatch) -> float:
    """Largest traced Python heap (MB) at the end of each chunk's filtering."""
    import v2v.pipeline as pipeline

    samples: list[int] = []
    run0 = pipeline.SolutionRunner.run

    def run(self, *a, **k):
        n = run0(self, *a, **k)
        samples.append(tracemalloc.get_traced_memory()[0])
        return n

    monkeypatch.setattr(pipeline.SolutionRunner, "run", run)
    tracemalloc.start()
    try:
        run_scenario(load_scenario(None, [f"duration_s={duration_s}", *ONE]), tmp_path / f"m{duration_s:.0f}",
                     quiet=True, replay=False, chunk_s=20.0)
    finally:
        tracemalloc.stop()
    return max(samples[len(samples) // 2:]) / 1e6  # second half: after start-up allocations (caches, numba)


@pytest.mark.slow
def test_memory_does_not_grow_with_duration(tmp_path, monkeypatch):
    """Heap while streaming, 240 s vs 120 s (3 vehicles, GPS+UWB+Bearing, 20 s chunks).

    What may grow with the run: the compact per-run numbers (UWB range errors for the summary,
    9 bytes per range: 3 pairs x 3 Hz x 120 s ~ 10 kB), the first 1000 traffic events, the
    membership log. Everything else is per chunk. Before streaming, the extra 120 s kept
    1200 SUMO steps, 3600 GNSS epochs, every UWB range / bearing as Python objects and the
    exchange's events (order 10-30 MB for these 3 vehicles). Bound: 2 MB, ~10x the allowed
    growth plus allocator noise, far below the old growth."""
    m120 = _streaming_heap_mb(tmp_path, 120.0, monkeypatch)
    m240 = _streaming_heap_mb(tmp_path, 240.0, monkeypatch)
    assert m240 - m120 < 2.0, (m120, m240)
