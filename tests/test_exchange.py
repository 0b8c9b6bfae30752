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


def test_loss_rate_within_binomial_bounds():
    p, n = 0.2, 20_000
    ex = V2VExchange(ExchangeConfig(loss_probability=p), "lead", np.random.default_rng(42))
    for i in range(n):
        ex.send(Message(i * 0.1, "a", "gnss", None))
    lo, hi = stats.binom.interval(0.999, n, p)  # false failure 0.1 %
    assert lo <= ex.stats.lost <= hi
