"""State-vector layout of the lead-vehicle-relative cluster filter.

The state is a concatenation of *blocks*. Every block has a kind and a key:

========== ===================== ===== =================================================
kind       key                   size  contents
========== ===================== ===== =================================================
vehicle    vehicle id            8     relative position ENU (3, m), relative velocity
                                       ENU (3, m/s), single-difference clock bias (m),
                                       single-difference clock drift (m/s), all relative
                                       to the lead (Petovello et al. section 3.2)
azimuth    vehicle id            1     absolute azimuth (rad, clockwise from north) of a
                                       bearing-measuring vehicle, the lead included
                                       (paper section 2.2, azimuth-unknown case)
az_rate    vehicle id            1     azimuth rate (yaw rate, rad/s) of a vehicle with an
                                       azimuth block (optional; see
                                       :mod:`v2v.estimation.process` for its model)
uwb        (id_a, id_b) sorted   2     UWB bias (m) and scale factor (unitless) of one
                                       radio pair (MacGougan (2009) eq. 3.4-3.5, 3.9)
sd_amb     (vehicle id, prn)     1     single-difference carrier-phase ambiguity
                                       ``N_v - N_lead`` (L1 cycles) of one satellite
                                       (MacGougan (2009) section 3.6; added when the
                                       satellite is tracked by both, removed at a slip
                                       or when it is lost)
========== ===================== ===== =================================================

Code elsewhere never does index arithmetic on the state: it asks the layout for
``position(v)``, ``clock(v)``, ``uwb_scale(pair)``, ``ambiguity(v, prn)`` ... The offsets,
the add/remove re-mapping and the process model are generic over block kinds.

The lead vehicle has no vehicle block (it is the origin); it may have an azimuth block.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError

F64 = NDArray[np.float64]

VEHICLE = "vehicle"
AZIMUTH = "azimuth"
AZIMUTH_RATE = "az_rate"
UWB = "uwb"
AMBIGUITY = "sd_amb"

#: Size of each block kind.
BLOCK_SIZES: dict[str, int] = {VEHICLE: 8, AZIMUTH: 1, AZIMUTH_RATE: 1, UWB: 2, AMBIGUITY: 1}

# Offsets inside a vehicle block.
_POS = slice(0, 3)
_VEL = slice(3, 6)
_CLK = 6
_DRIFT = 7

BlockId = tuple[str, Hashable]
Remap = Callable[[F64, F64], tuple[F64, F64]]
# Blocks seen with the key type of their kind (str, (str, str) or (str, int)), which the type checker
# cannot tell from the kind: for reading keys of a known kind.
_KindKeyedBlocks = tuple[tuple[str, Any], ...]


def uwb_pair_key(a: str, b: str) -> tuple[str, str]:
    """Canonical (sorted) key of the radio pair a-b: a two-way range is symmetric."""
    if a == b:
        raise UserError(f"UWB pair needs two different vehicles, got {a!r} twice", field="uwb_pairs")
    return (a, b) if a < b else (b, a)


@dataclass(frozen=True, kw_only=True)
class StateLayout:
    """Ordered state blocks of the cluster filter.

    Parameters
    ----------
    lead : str
        Lead vehicle id (the origin of all relative states; no vehicle block).
    blocks : tuple of (kind, key)
        Blocks in state order. Use :meth:`build` to create a layout.
    """

    lead: str
    blocks: tuple[BlockId, ...]
    _offsets: dict[BlockId, int] = field(init=False, repr=False, compare=False)
    _vehicles: tuple[str, ...] = field(init=False, repr=False, compare=False)
    #: ``position(v).start`` / ``velocity(v).start`` of every non-lead vehicle (read per epoch)
    position_starts: dict[str, int] = field(init=False, repr=False, compare=False)
    velocity_starts: dict[str, int] = field(init=False, repr=False, compare=False)
    n: int = field(init=False)

    def __post_init__(self) -> None:
        offsets: dict[BlockId, int] = {}
        i = 0
        for kind, key in self.blocks:
            if kind not in BLOCK_SIZES:
                raise UserError(f"unknown state block kind {kind!r}", field="layout.blocks")
            if (kind, key) in offsets:
                raise UserError(f"state block {kind}:{key!r} listed twice", field="layout.blocks")
            if kind == VEHICLE and key == self.lead:
                raise UserError("the lead vehicle has no relative-state block", field="layout.vehicles")
            offsets[(kind, key)] = i
            i += BLOCK_SIZES[kind]
        for kind, key in self.blocks:
            if kind == AZIMUTH_RATE and (AZIMUTH, key) not in offsets:
                raise UserError(f"azimuth-rate block of {key!r} has no azimuth block", field="layout.blocks")
        object.__setattr__(self, "_offsets", offsets)
        object.__setattr__(self, "_vehicles", tuple(k for kind, k in self.blocks if kind == VEHICLE))
        object.__setattr__(self, "position_starts", {v: offsets[(VEHICLE, v)] + _POS.start for v in self._vehicles})
        object.__setattr__(self, "velocity_starts", {v: offsets[(VEHICLE, v)] + _VEL.start for v in self._vehicles})
        object.__setattr__(self, "n", i)

    # ------------------------------------------------------------------ building
    @classmethod
    def build(
        cls,
        *,
        lead: str,
        vehicles: tuple[str, ...] | list[str],
        azimuth_vehicles: tuple[str, ...] | list[str] = (),
        uwb_pairs: tuple[tuple[str, str], ...] | list[tuple[str, str]] = (),
        azimuth_rates: bool = False,
    ) -> StateLayout:
        """Layout with vehicle blocks first, then azimuth blocks (each followed by its
        azimuth-rate block when ``azimuth_rates``), then UWB pair blocks."""
        known = {lead, *vehicles}
        for v in azimuth_vehicles:
            if v not in known:
                raise UserError(f"azimuth vehicle {v!r} is not in the cluster", field="azimuth_vehicles")
        pairs = []
        for a, b in uwb_pairs:
            if a not in known or b not in known:
                raise UserError(f"UWB pair ({a!r}, {b!r}) names a vehicle not in the cluster", field="uwb_pairs")
            pairs.append(uwb_pair_key(a, b))
        blocks = (
            [(VEHICLE, v) for v in vehicles]
            + [b for v in azimuth_vehicles for b in ([(AZIMUTH, v), (AZIMUTH_RATE, v)] if azimuth_rates else [(AZIMUTH, v)])]
            + [(UWB, p) for p in pairs]
        )
        return cls(lead=lead, blocks=tuple(blocks))

    # ------------------------------------------------------------------ queries
    @property
    def vehicles(self) -> tuple[str, ...]:
        """Non-lead vehicles, in state order."""
        return self._vehicles

    @property
    def azimuth_vehicles(self) -> tuple[str, ...]:
        return cast("tuple[str, ...]", tuple(k for kind, k in self.blocks if kind == AZIMUTH))

    @property
    def azimuth_rate_vehicles(self) -> tuple[str, ...]:
        return cast("tuple[str, ...]", tuple(k for kind, k in self.blocks if kind == AZIMUTH_RATE))

    @property
    def uwb_pairs(self) -> tuple[tuple[str, str], ...]:
        return cast("tuple[tuple[str, str], ...]", tuple(k for kind, k in self.blocks if kind == UWB))

    def ambiguity_keys(self, v: str | None = None) -> tuple[tuple[str, int], ...]:
        """``(vehicle, prn)`` keys of the SD ambiguity blocks (of ``v`` only when given), state order."""
        blocks = cast(_KindKeyedBlocks, self.blocks)
        return tuple(k for kind, k in blocks if kind == AMBIGUITY and (v is None or k[0] == v))

    def ambiguity(self, v: str, prn: int) -> int:
        """SD carrier-phase ambiguity ``N_v - N_lead`` (cycles) of satellite ``prn``."""
        return self.block(AMBIGUITY, (v, int(prn))).start

    def without_blocks(self, ids: Sequence[BlockId]) -> tuple[StateLayout, Remap]:
        """Remove the listed blocks (marginalization: the other rows/columns of x, P are kept)."""
        drop = set(ids)
        new = StateLayout(lead=self.lead, blocks=tuple(b for b in self.blocks if b not in drop))
        return new, _make_remap(self, new, {})

    def with_blocks(self, kind: str, keys: Sequence[Hashable], *, mean: F64, variance: F64
                    ) -> tuple[StateLayout, Remap]:
        """Append several blocks of one single-state kind (e.g. ambiguities) in one remap;
        ``mean``/``variance`` (k,) per block, uncorrelated with the rest."""
        if BLOCK_SIZES[kind] != 1:
            raise ValueError("with_blocks is for single-state block kinds")
        for key in keys:
            if self.has(kind, key):
                raise UserError(f"state block {kind}:{key!r} already exists", field="layout")
        new = StateLayout(lead=self.lead, blocks=self.blocks + tuple((kind, k) for k in keys))
        m = np.asarray(mean, dtype=float).reshape(-1)
        var = np.asarray(variance, dtype=float).reshape(-1)
        return new, _make_remap(self, new, {(kind, k): (m[i:i + 1], var[i:i + 1]) for i, k in enumerate(keys)})

    def has(self, kind: str, key: Hashable) -> bool:
        return (kind, key) in self._offsets

    def block(self, kind: str, key: Hashable) -> slice:
        """Slice of a whole block."""
        try:
            i = self._offsets[(kind, key)]
        except KeyError:
            raise KeyError(f"no {kind} block for {key!r} in this layout") from None
        return slice(i, i + BLOCK_SIZES[kind])

    def _veh(self, v: str) -> int:
        return self.block(VEHICLE, v).start

    def position(self, v: str) -> slice:
        """Relative position ENU (m) of non-lead vehicle ``v``."""
        i = self._veh(v)
        return slice(i + _POS.start, i + _POS.stop)

    def velocity(self, v: str) -> slice:
        """Relative velocity ENU (m/s) of non-lead vehicle ``v``."""
        i = self._veh(v)
        return slice(i + _VEL.start, i + _VEL.stop)

    def clock(self, v: str) -> int:
        """Single-difference clock bias (m) of ``v`` minus the lead."""
        return self._veh(v) + _CLK

    def drift(self, v: str) -> int:
        """Single-difference clock drift (m/s)."""
        return self._veh(v) + _DRIFT

    def azimuth(self, v: str) -> int:
        """Absolute azimuth (rad, clockwise from north) of bearing-measuring vehicle ``v``."""
        return self.block(AZIMUTH, v).start

    def azimuth_rate(self, v: str) -> int:
        """Azimuth rate (yaw rate, rad/s, clockwise positive) of ``v``, when the layout has it."""
        return self.block(AZIMUTH_RATE, v).start

    def uwb_bias(self, pair: tuple[str, str]) -> int:
        """UWB range bias (m) of a radio pair (order of the pair does not matter)."""
        return self.block(UWB, uwb_pair_key(*pair)).start

    def uwb_scale(self, pair: tuple[str, str]) -> int:
        """UWB scale-factor error s (unitless; R = (1 + s) rho + b) of a radio pair."""
        return self.block(UWB, uwb_pair_key(*pair)).start + 1

    def vehicle_blocks_contiguous(self) -> tuple[int, int]:
        """(start, count) when all vehicle blocks are contiguous (true for :meth:`build`)."""
        starts = [self._offsets[(VEHICLE, v)] for v in self.vehicles]
        if not starts:
            return 0, 0
        s0 = starts[0]
        if starts != list(range(s0, s0 + 8 * len(starts), 8)):
            raise ValueError("vehicle blocks are not contiguous")
        return s0, len(starts)

    # ------------------------------------------------------------------ editing
    def with_block(self, kind: str, key: Hashable, *, mean: F64 | float, variance: F64 | float
                   ) -> tuple[StateLayout, Remap]:
        """Insert a block (vehicle blocks after the last vehicle block, others at the end).

        Returns the new layout and ``remap(x, P) -> (x_new, P_new)``: existing blocks keep
        their values and cross-covariances; the new block gets ``mean`` and a diagonal
        covariance ``variance`` (scalar or per element), uncorrelated with the rest.
        """
        if kind == UWB:
            key = uwb_pair_key(*cast("tuple[str, str]", key))
        if self.has(kind, key):
            raise UserError(f"state block {kind}:{key!r} already exists", field="layout")
        blocks = list(self.blocks)
        if kind == VEHICLE:
            last = max((i for i, (k, _) in enumerate(blocks) if k == VEHICLE), default=-1)
            blocks.insert(last + 1, (kind, key))
        else:
            blocks.append((kind, key))
        new = StateLayout(lead=self.lead, blocks=tuple(blocks))
        size = BLOCK_SIZES[kind]
        m = np.broadcast_to(np.asarray(mean, dtype=float), (size,))
        var = np.broadcast_to(np.asarray(variance, dtype=float), (size,))
        return new, _make_remap(self, new, {(kind, key): (m, var)})

    def add_vehicle(self, v: str, *, mean: F64, variance: F64 | float) -> tuple[StateLayout, Remap]:
        """Add a non-lead vehicle block (8 states: see the module table)."""
        if v == self.lead:
            raise UserError("the lead vehicle has no relative-state block", field="vehicle")
        return self.with_block(VEHICLE, v, mean=mean, variance=variance)

    def without_vehicle(self, v: str) -> tuple[StateLayout, Remap]:
        """Remove vehicle ``v``: its block, its azimuth (and rate) block, every UWB pair it is in
        and its SD ambiguities.

        Removing a block marginalizes it: the remaining rows/columns of x and P are kept.
        """
        keep = tuple(
            (kind, key)
            for kind, key in cast(_KindKeyedBlocks, self.blocks)
            if not (key == v and kind in (VEHICLE, AZIMUTH, AZIMUTH_RATE)) and not (kind == UWB and v in key)
            and not (kind == AMBIGUITY and key[0] == v)
        )
        new = StateLayout(lead=self.lead, blocks=keep)
        return new, _make_remap(self, new, {})


def _make_remap(old: StateLayout, new: StateLayout, init: dict[BlockId, tuple[F64, F64]]) -> Remap:
    src: list[int] = []
    dst: list[int] = []
    for bid in new.blocks:
        if bid in old._offsets:
            o = old.block(*bid)
            d = new.block(*bid)
            src.extend(range(o.start, o.stop))
            dst.extend(range(d.start, d.stop))
    src_i = np.asarray(src, dtype=int)
    dst_i = np.asarray(dst, dtype=int)

    def remap(x: F64, P: F64) -> tuple[F64, F64]:
        if x.shape != (old.n,) or P.shape != (old.n, old.n):
            raise ValueError(f"remap expects x ({old.n},) and P ({old.n},{old.n})")
        x_new = np.zeros(new.n)
        P_new = np.zeros((new.n, new.n))
        x_new[dst_i] = x[src_i]
        P_new[np.ix_(dst_i, dst_i)] = P[np.ix_(src_i, src_i)]
        for bid, (m, var) in init.items():
            s = new.block(*bid)
            x_new[s] = m
            P_new[s, s] = np.diag(var)
        return x_new, P_new

    return remap
