"""V2V exchange: latency, loss (binomial bounds), time-tag ordering, late messages."""

from __future__ import annotations

import numpy as np
from scipy import stats

from v2v.exchange import ExchangeConfig, Message, V2VExchange


def test_no_latency_delivers_everything_in_time_order():
    ex = V2VExchange(ExchangeConfig(), "lead", np.random.default_rng(0))
    ex.send(Message(0.2, "b", "gnss", 2))
    ex.send(Message(0.1, "a", "gnss", 1))
    ex.send(Message(0.1, "lead", "gnss", 0))
    got = ex.deliver(0.2)
    assert [m.t_s for m in got] == [0.1, 0.1, 0.2]
    assert ex.deliver(0.3) == []


def test_latency_holds_messages_and_lag_keeps_time_tags():
    ex = V2VExchange(ExchangeConfig(latency_s=0.25), "lead", np.random.default_rng(0))
    ex.send(Message(1.0, "a", "uwb", "x"))
    ex.send(Message(1.0, "lead", "gnss", "own"))
    assert ex.deliver(1.0) == []  # the filter runs 0.25 s behind
    got = ex.deliver(1.25)
    assert sorted((m.sender, m.t_s) for m in got) == [("a", 1.0), ("lead", 1.0)]


def test_late_message_is_counted_and_dropped():
    ex = V2VExchange(ExchangeConfig(latency_s=0.5, filter_lag_s=0.1), "lead", np.random.default_rng(0))
    ex.send(Message(1.0, "a", "gnss", None))
    assert ex.deliver(1.2) == []  # processed up to 1.1 already, message still in flight
    assert ex.deliver(1.6) == [] and ex.stats.late == 1


def test_a_message_tagged_at_the_last_horizon_is_on_time_whatever_the_rounding():
    """Latency 0.15 s, lag 0.1 s, deliveries on a 10 Hz grid: a message tagged t misses the
    delivery at t + 0.1 (horizon t) and arrives before the one at t + 0.2, whose last horizon
    is its own time tag: the filter is still at t, so it is delivered (applied at t), never
    late. Before, (t + 0.1 - 0.1 + 1e-9) - 1e-9 rounding above t (t = 0.7: 0.7000000000000001)
    made some of them late and not others. One tagged before the last horizon is late."""
    cfg = ExchangeConfig(latency_s=0.15, filter_lag_s=0.1)
    ex = V2VExchange(cfg, "lead", np.random.default_rng(0))
    grid = [round(0.1 * k, 10) for k in range(60)]
    got = []
    for k, now in enumerate(grid):
        ex.send(Message(now, "a", "gnss", k))
        got += [m.payload for m in ex.deliver(now)]
    assert ex.stats.late == 0 and got == list(range(len(grid) - 2))  # (the last two still in flight)
    ex2 = V2VExchange(ExchangeConfig(latency_s=0.25, filter_lag_s=0.1), "lead", np.random.default_rng(0))
    ex2.send(Message(0.7, "a", "gnss", None))
    assert [ex2.deliver(t) for t in (0.8, 0.9, 1.0)] == [[], [], []] and ex2.stats.late == 1  # 0.7 < horizon 0.8


def test_loss_rate_within_binomial_bounds():
    p, n = 0.2, 20_000
    ex = V2VExchange(ExchangeConfig(loss_probability=p), "lead", np.random.default_rng(42))
    for i in range(n):
        ex.send(Message(i * 0.1, "a", "gnss", None))
    lo, hi = stats.binom.interval(0.999, n, p)  # false failure 0.1 %
    assert lo <= ex.stats.lost <= hi


def _bearings(t, a, b):
    from v2v.sensors.measurements import Bearings

    k = np.arange(len(t), dtype=float)
    return Bearings(t_s=np.asarray(t, dtype=float), a=tuple(a), b=tuple(b), bearing_rad=k, true_bearing_rad=k,
                    azimuth_reported_rad=k, true_azimuth_rad=k, los=np.ones(len(t), dtype=bool))


def test_bearings_travel_as_one_packet_per_vehicle_and_time_tag():
    """The exchange model: a vehicle's bearings of one instant are one message, delivered or
    lost as a whole; the filter gets each time tag's delivered bearings in measurement
    order. Hand-built: 3 vehicles, 2 time tags, rows interleaved (4 packets from "a" and
    "b", 2 from the lead, which need no radio). The packets' send order (first occurrence)
    is checked too: it decides which loss draw each packet gets, i.e. reproducibility."""
    from v2v.pipeline import ExchangeStream

    t = [0.1, 0.1, 0.1, 0.2, 0.1, 0.2, 0.2, 0.2, 0.1]
    a = ["a", "b", "a", "lead", "lead", "a", "b", "a", "b"]
    b = ["b", "a", "lead", "a", "b", "lead", "lead", "b", "lead"]
    xs = ExchangeStream(V2VExchange(ExchangeConfig(), "lead", np.random.default_rng(0)), lambda eps: [None] * len(eps))
    xs.add_bearings(_bearings(t, a, b))
    packets = [(m.t_s, m.sender, list(m.payload[1])) for _, _, _, m in xs._msgs]
    assert packets == [(0.1, "a", [0, 2]), (0.1, "b", [1, 8]), (0.2, "lead", [3]), (0.1, "lead", [4]),
                       (0.2, "a", [5, 7]), (0.2, "b", [6])]  # first occurrence order, rows in order
    for tk in (0.1, 0.2):
        xs.add_output_time(tk)
    events = xs.advance(np.inf, final=True)
    assert [e.t_s for e in events] == [0.1, 0.2]
    assert [e.bearings.bearing_rad.tolist() for e in events] == [[0, 1, 2, 4, 8], [3, 5, 6, 7]]
    assert [list(zip(e.bearings.a, e.bearings.b, strict=True)) for e in events] == [
        [("a", "b"), ("b", "a"), ("a", "lead"), ("lead", "b"), ("b", "lead")],
        [("lead", "a"), ("a", "lead"), ("b", "lead"), ("a", "b")]]
    assert xs.exchange.stats.sent == 4  # the lead's two packets are on board


def test_lost_bearing_packet_takes_all_its_bearings():
    """Loss probability 1 for every radio message: only the lead's own bearings arrive."""
    from v2v.pipeline import ExchangeStream

    xs = ExchangeStream(V2VExchange(ExchangeConfig(loss_probability=1.0), "lead", np.random.default_rng(0)),
                        lambda eps: [None] * len(eps))
    xs.add_bearings(_bearings([0.1, 0.1, 0.1], ["a", "lead", "a"], ["lead", "a", "b"]))
    xs.add_output_time(0.1)
    (ev,) = xs.advance(np.inf, final=True)
    assert ev.bearings.a == ("lead",) and xs.exchange.stats.lost == 1
