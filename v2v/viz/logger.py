"""The replay-logger interface and its do-nothing implementation.

Pipeline code (``v2v.run`` and the experiments) logs a run through :class:`ReplayLogger`
and never imports rerun: :class:`~v2v.viz.rerun_logger.RerunReplayLogger` is the one
implementation that does (STYLE.md, "one boundary per outside system"), and
:class:`NullLogger` accepts every call and does nothing (tests, ``--no-replay``).

Conventions of every call
-------------------------
* ``t_s``: simulation time in seconds (the ``sim_time`` timeline of the recording).
* Positions are **net XY** metres (plus height ``z`` where 3-D), see :mod:`v2v.frames`.
* Covariances ``cov_en_m2`` are east/north (ENU) in m²; the logger rotates them into
  net XY by the projection's grid convergence before drawing.
* Angles are radians; azimuths clockwise from true north.

A logger is used once: log, then :meth:`ReplayLogger.close` (writes the file atomically)
or :meth:`ReplayLogger.abort` (writes nothing). As a context manager it closes on success
and aborts when the block raises, so a failed run never leaves a replay that looks whole::

    with RerunReplayLogger(out / "replay.rrd") as replay:
        replay.log_world(...)
        for step in steps:
            replay.log_truth(step.t_s, step)

Many rows at once: ``log_truth_many``, ``log_links_many``, ``log_satellites_many`` and
``log_epochs`` log the rows of many steps or epochs in one call (what the per-step calls
would log, in order); the defaults here loop over the per-step methods, an implementation
overrides them to vectorize (``v2v.run`` logs each 30 s chunk's truth, links and sky plots,
and each solution's estimates and errors of the chunk, this way).

The entity layout of the recording is documented in :mod:`v2v.viz.blueprint`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from v2v.frames import GeoReference
from v2v.traffic.snapshot import TrafficStep

LINK_KINDS = ("uwb", "bearing")
LINK_STATUSES = ("los", "nlos", "rejected")


class Footprint(Protocol):
    """What the logger needs from a building or foliage area (``v2v.world.buildings``)."""

    id: str
    footprint_xy_m: NDArray[np.float64]  # (K, 2) net XY, not closed
    height_m: float


class ReplayLogger(ABC):
    """Everything a run shows in its replay. See the module docstring for conventions."""

    @abstractmethod
    def log_world(
        self,
        lanes: Mapping[str, ArrayLike],
        lane_widths: Mapping[str, float],
        buildings: Sequence[Footprint],
        foliage: Sequence[Footprint],
        geo: GeoReference,
    ) -> None:
        """Static scene, logged once: lane centre lines ``(k, 2)`` (or ``(k, 3)``) in net
        XY with their widths in metres, extruded buildings and foliage, and the
        geo-reference used for the map view and the ENU -> net XY rotation."""

    @abstractmethod
    def log_truth(self, t_s: float, step: TrafficStep) -> None:
        """True vehicles at ``t_s`` as 3-D boxes (and geodetic points for the map)."""

    @abstractmethod
    def log_estimates(
        self,
        t_s: float,
        solution: str,
        vehicle_ids: Sequence[str],
        est_xy_m: ArrayLike,
        cov_en_m2: ArrayLike,
        cluster: str = "",
    ) -> None:
        """Estimated positions ``(n, 2)`` net XY of one solution with their horizontal
        covariance ``(n, 2, 2)`` (east/north, m²), drawn as uncertainty ellipses. ``cluster``
        (a run with several clusters): the cluster's own entities, so that the clusters' rows
        at the same time do not replace each other."""

    @abstractmethod
    def log_links(
        self,
        t_s: float,
        kind: str,
        a_xyz_m: ArrayLike,
        b_xyz_m: ArrayLike,
        status: Sequence[str],
    ) -> None:
        """Radio (``kind="uwb"``) or bearing (``"bearing"``) links ``a -> b``, ``(m, 3)``
        each, coloured by ``status`` in ``("los", "nlos", "rejected")``. ``m = 0`` clears
        the links of that kind."""

    @abstractmethod
    def log_satellites(
        self,
        t_s: float,
        vehicle_id: str,
        prn: ArrayLike,
        az_rad: ArrayLike,
        el_rad: ArrayLike,
        los: ArrayLike,
    ) -> None:
        """Satellites tracked by one vehicle: sky plot coloured line-of-sight / NLOS."""

    @abstractmethod
    def log_errors(
        self,
        t_s: float,
        solution: str,
        vehicle_id: str,
        along_m: float,
        across_m: float,
        sigma_along_m: float,
        sigma_across_m: float,
        nees: float,
        nis: float,
        n_sats: int,
        rejections: int,
    ) -> None:
        """One row of the error time series of ``vehicle_id`` under ``solution``."""

    # -- batches: one call for many rows. The defaults log row by row; an implementation
    # overrides them when it can do better (RerunReplayLogger vectorizes them).

    def log_truth_many(self, steps: Sequence[TrafficStep]) -> None:
        """:meth:`log_truth` of each step, at its own ``step.t_s``, in order."""
        for step in steps:
            self.log_truth(step.t_s, step)

    def log_links_many(
        self,
        t_s: ArrayLike,
        kind: str,
        counts: ArrayLike,
        a_xyz_m: ArrayLike,
        b_xyz_m: ArrayLike,
        status: Sequence[str],
    ) -> None:
        """:meth:`log_links` at each time ``t_s[j]`` with its ``counts[j]`` links: ``a_xyz_m``,
        ``b_xyz_m`` ``(sum(counts), 3)`` and ``status`` hold the rows one after another."""
        a = np.asarray(a_xyz_m, dtype=float).reshape(-1, 3)
        b = np.asarray(b_xyz_m, dtype=float).reshape(-1, 3)
        status = list(status)
        lo = 0
        for t, m in zip(np.asarray(t_s, dtype=float).tolist(), np.asarray(counts, dtype=int).tolist(), strict=True):
            self.log_links(t, kind, a[lo : lo + m], b[lo : lo + m], status[lo : lo + m])
            lo += m

    def log_satellites_many(
        self,
        t_s: ArrayLike,
        vehicle_ids: Sequence[str],
        counts: ArrayLike,
        prn: ArrayLike,
        az_rad: ArrayLike,
        el_rad: ArrayLike,
        los: ArrayLike,
    ) -> None:
        """:meth:`log_satellites` of ``vehicle_ids[j]`` at ``t_s[j]`` with its ``counts[j]``
        satellites: ``prn``, ``az_rad``, ``el_rad``, ``los`` hold the rows one after another."""
        prn, az, el, ok = (np.asarray(x).reshape(-1) for x in (prn, az_rad, el_rad, los))
        lo = 0
        for t, v, m in zip(np.asarray(t_s, dtype=float).tolist(), vehicle_ids,
                           np.asarray(counts, dtype=int).tolist(), strict=True):
            self.log_satellites(t, v, prn[lo : lo + m], az[lo : lo + m], el[lo : lo + m], ok[lo : lo + m])
            lo += m

    def log_errors_many(self, t_s: float, solution: str, vehicle_ids: Sequence[str],
                        rows: Sequence[Sequence[float]]) -> None:
        """:meth:`log_errors` of several vehicles at one time: ``rows[j]`` holds the values
        of ``vehicle_ids[j]`` in :meth:`log_errors`' order (along_m, across_m, sigma_along_m,
        sigma_across_m, nees, nis, n_sats, rejections)."""
        if len(rows) != len(vehicle_ids) or any(len(r) != 8 for r in rows):
            raise ValueError(f"log_errors_many: {len(vehicle_ids)} vehicle ids and {len(rows)} rows "
                             "of 8 numbers each expected")
        for v, row in zip(vehicle_ids, rows, strict=True):
            along, across, s_along, s_across, nees, nis, n_sats, rejections = row
            self.log_errors(t_s, solution, v, along, across, s_along, s_across, nees, nis, int(n_sats), int(rejections))

    def log_epochs(
        self,
        t_s: ArrayLike,
        solution: str,
        counts: ArrayLike,
        vehicle_ids: Sequence[str],
        est_xy_m: ArrayLike,
        cov_en_m2: ArrayLike,
        errors: ArrayLike,
        cluster: str = "",
    ) -> None:
        """Several epochs of one solution: at each time ``t_s[k]``, :meth:`log_errors_many`
        and :meth:`log_estimates` (of ``cluster``) of its ``counts[k]`` vehicles. ``vehicle_ids``, ``est_xy_m``
        ``(sum(counts), 2)``, ``cov_en_m2`` ``(sum(counts), 2, 2)`` and ``errors``
        ``(sum(counts), 8)`` (:meth:`log_errors`' order) hold the epochs' rows one after
        another."""
        xy = np.asarray(est_xy_m, dtype=float).reshape(-1, 2)
        cov = np.asarray(cov_en_m2, dtype=float).reshape(-1, 2, 2)
        err = np.asarray(errors, dtype=float).reshape(-1, 8)
        ids = list(vehicle_ids)
        if not (len(xy) == len(cov) == len(err) == len(ids)):
            raise ValueError(f"log_epochs: {len(ids)} vehicle ids, {len(xy)} positions, {len(cov)} covariances, "
                             f"{len(err)} error rows")
        lo = 0
        for t, m in zip(np.asarray(t_s, dtype=float).reshape(-1).tolist(),
                        np.asarray(counts, dtype=int).reshape(-1).tolist(), strict=True):
            self.log_errors_many(t, solution, ids[lo : lo + m], err[lo : lo + m].tolist())
            # cluster only when given: a logger written before it existed still serves one cluster
            self.log_estimates(t, solution, ids[lo : lo + m], xy[lo : lo + m], cov[lo : lo + m],
                               **({"cluster": cluster} if cluster else {}))
            lo += m

    def log_error_gaps(self, t_s: ArrayLike, solution: str, vehicle_ids: Sequence[str]) -> None:  # noqa: B027
        """At each ``t_s[j]``, ``vehicle_ids[j]``'s error series of ``solution`` stop: the vehicle
        has no estimate from there until its next :meth:`log_errors` row (it left the cluster
        or was re-initialized), so a plot must not join the rows on either side of the gap
        with a line. Optional hook: nothing by default."""

    @abstractmethod
    def close(self) -> None:
        """Flush everything and publish the recording (atomically). Idempotent."""

    def abort(self) -> None:  # noqa: B027 - optional hook, nothing to discard by default
        """Discard the recording without publishing it. Idempotent."""

    def __enter__(self) -> ReplayLogger:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class NullLogger(ReplayLogger):
    """Accepts every call and records nothing (tests, ``--no-replay``)."""

    def log_world(self, lanes, lane_widths, buildings, foliage, geo) -> None:
        pass

    def log_truth(self, t_s, step) -> None:
        pass

    def log_estimates(self, t_s, solution, vehicle_ids, est_xy_m, cov_en_m2, cluster="") -> None:
        pass

    def log_links(self, t_s, kind, a_xyz_m, b_xyz_m, status) -> None:
        pass

    def log_truth_many(self, steps) -> None:
        pass

    def log_links_many(self, t_s, kind, counts, a_xyz_m, b_xyz_m, status) -> None:
        pass

    def log_satellites_many(self, t_s, vehicle_ids, counts, prn, az_rad, el_rad, los) -> None:
        pass

    def log_satellites(self, t_s, vehicle_id, prn, az_rad, el_rad, los) -> None:
        pass

    def log_errors(
        self,
        t_s,
        solution,
        vehicle_id,
        along_m,
        across_m,
        sigma_along_m,
        sigma_across_m,
        nees,
        nis,
        n_sats,
        rejections,
    ) -> None:
        pass

    def log_errors_many(self, t_s, solution, vehicle_ids, rows) -> None:
        pass

    def log_epochs(self, t_s, solution, counts, vehicle_ids, est_xy_m, cov_en_m2, errors, cluster="") -> None:
        pass

    def log_error_gaps(self, t_s, solution, vehicle_ids) -> None:
        pass

    def close(self) -> None:
        pass
