"""V2V exchange: what the lead vehicle's filter receives from the other vehicles.

Each non-lead vehicle broadcasts, per epoch, its GNSS observations and the UWB ranges it
initiated and bearings it measured. The lead's own measurements need no network. Every
message is delayed by ``latency_s`` and lost with probability ``loss_probability``
(independently per message; bursts of loss are a fault to inject, see the faults section).

The filter applies every measurement at its own time tag. To do that with late
messages it runs ``filter_lag_s`` behind real time (default: the latency): at time ``t``
it processes everything time-tagged up to ``t - filter_lag_s``. A message that arrives
after its time tag has been processed is counted as *late* and dropped: one whose time tag
is before the horizon of the last delivery. One tagged at that horizon (within 1e-9 s) is
not late: the filter is still at that time, so it is applied at its time tag, after the
output epoch at that time (before 2026-12-06 such a message was late or not by the
rounding of ``now - lag``). The filter advances at the output epochs, so whether a
message is late depends on them too: it is late when an output epoch's horizon passes its
time tag before it arrives (with ``latency_s`` a little over ``filter_lag_s``, most
messages at a 10 Hz output, few at 1 Hz).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from v2v.config.sections import ExchangeSection

ExchangeConfig = ExchangeSection  # scenario section [exchange]


@dataclass(frozen=True, slots=True)
class Message:
    t_s: float  # the payload's time tag
    sender: str
    kind: str  # "gnss" | "uwb" | "bearing"
    payload: Any


@dataclass
class ExchangeStats:
    sent: int = 0
    lost: int = 0
    late: int = 0
    delivered: int = 0

    def __iadd__(self, other: ExchangeStats) -> ExchangeStats:
        """Add ``other``'s counts (the links of several clusters' leads)."""
        self.sent, self.lost = self.sent + other.sent, self.lost + other.lost
        self.late, self.delivered = self.late + other.late, self.delivered + other.delivered
        return self


class V2VExchange:
    """Delivers messages to the lead's filter in time-tag order, after latency and loss."""

    def __init__(self, config: ExchangeConfig, lead_id: str, rng: np.random.Generator):
        self.config = config
        self.lead_id = lead_id
        self.rng = rng
        self.stats = ExchangeStats()
        self._in_flight: list[tuple[float, int, Message]] = []  # (arrival time, seq, message)
        self._arrived: list[tuple[float, int, Message]] = []  # (time tag, seq, message)
        self._seq = itertools.count()
        self._processed_until_s = -np.inf

    def send(self, msg: Message) -> None:
        self.send_many((msg,))

    def send_many(self, msgs: Iterable[Message]) -> None:
        """:meth:`send` of each message in turn (the same loss draws, in the same order)."""
        lead, p, latency = self.lead_id, self.config.loss_probability, self.config.latency_s
        arrived, in_flight, seq, push = self._arrived, self._in_flight, self._seq, heapq.heappush
        draw = self.rng.random
        sent = lost = 0
        for msg in msgs:
            if msg.sender == lead:  # on board the lead: no radio link
                push(arrived, (msg.t_s, next(seq), msg))
                continue
            sent += 1
            if p > 0.0 and draw() < p:
                lost += 1
                continue
            push(in_flight, (msg.t_s + latency, next(seq), msg))
        self.stats.sent += sent
        self.stats.lost += lost

    @property
    def processed_until_s(self) -> float:
        """The filter's horizon so far (plus 1e-9 s): every message delivered later has a time
        tag ``>= processed_until_s - 2e-9`` (earlier ones are counted late and dropped), which is
        what lets a chunked run hand the filter a chunk's events before the next chunk exists."""
        return self._processed_until_s

    def deliver(self, now_s: float) -> list[Message]:
        """Messages whose time tags the filter may process at ``now_s``, in time-tag order."""
        in_flight, arrived, pop, push = self._in_flight, self._arrived, heapq.heappop, heapq.heappush
        due = now_s + 1e-9
        # before the last horizon (processed_until_s less its 1e-9) by more than 1e-9: a tag at
        # the horizon itself is on time whichever way now - lag rounded (changes only below,
        # after the arrivals)
        too_late = self._processed_until_s - 2e-9
        late = 0
        while in_flight and in_flight[0][0] <= due:
            _, seq, msg = pop(in_flight)
            if msg.t_s < too_late:
                late += 1
                continue
            push(arrived, (msg.t_s, seq, msg))
        self.stats.late += late
        horizon = now_s - self.config.lag_s + 1e-9
        out = []
        while arrived and arrived[0][0] <= horizon:
            out.append(pop(arrived)[2])
        self._processed_until_s = max(self._processed_until_s, horizon)
        lead = self.lead_id
        self.stats.delivered += sum(1 for m in out if m.sender != lead)
        return out
