"""V2V exchange: what the lead vehicle's filter receives from the other vehicles.

Each non-lead vehicle broadcasts, per epoch, its GNSS observations and the UWB ranges it
initiated and bearings it measured. The lead's own measurements need no network. Every
message is delayed by ``latency_s`` and lost with probability ``loss_probability``
(independently per message; bursts of loss are a fault to inject, see the faults section).

The filter applies every measurement at its own time tag. To do that with late
messages it runs ``filter_lag_s`` behind real time (default: the latency): at time ``t``
it processes everything time-tagged up to ``t - filter_lag_s``. A message that arrives
after its time tag has been processed is counted as *late* and dropped.
"""

from __future__ import annotations

import heapq
import itertools
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
        if msg.sender == self.lead_id:  # on board the lead: no radio link
            heapq.heappush(self._arrived, (msg.t_s, next(self._seq), msg))
            return
        self.stats.sent += 1
        if self.config.loss_probability > 0.0 and self.rng.random() < self.config.loss_probability:
            self.stats.lost += 1
            return
        heapq.heappush(self._in_flight, (msg.t_s + self.config.latency_s, next(self._seq), msg))

    @property
    def processed_until_s(self) -> float:
        """The filter's horizon so far: every message delivered later has a time tag
        ``>= processed_until_s - 1e-9`` (earlier ones are counted late and dropped), which is
        what lets a chunked run hand the filter a chunk's events before the next chunk exists."""
        return self._processed_until_s

    def deliver(self, now_s: float) -> list[Message]:
        """Messages whose time tags the filter may process at ``now_s``, in time-tag order."""
        while self._in_flight and self._in_flight[0][0] <= now_s + 1e-9:
            _, seq, msg = heapq.heappop(self._in_flight)
            if msg.t_s < self._processed_until_s - 1e-9:
                self.stats.late += 1
                continue
            heapq.heappush(self._arrived, (msg.t_s, seq, msg))
        horizon = now_s - self.config.lag_s + 1e-9
        out = []
        while self._arrived and self._arrived[0][0] <= horizon:
            out.append(heapq.heappop(self._arrived)[2])
        self._processed_until_s = max(self._processed_until_s, horizon)
        self.stats.delivered += sum(1 for m in out if m.sender != self.lead_id)
        return out
