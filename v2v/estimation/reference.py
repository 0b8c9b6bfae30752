"""Reference engine: the same cluster filter written plainly on filterpy.

Everything the production engine does with sparse rows and block-wise prediction is
done here with full dense matrices through ``filterpy.kalman.ExtendedKalmanFilter``:
``predict()`` with the dense block-diagonal F, Q of :func:`v2v.estimation.process.transition`,
and one ``update()`` per scalar measurement with a dense (1, n) H, z passed as a (1, 1)
array (a 1-D z silently broadcasts in filterpy, rlabbe/filterpy #225) and never
``predict_update`` (it linearizes at the wrong point, #271). filterpy updates P in Joseph
form. Sequencing, gating and initialization are inherited from
:class:`v2v.estimation.filter.ClusterFilterBase`, so both engines must give the same
answer to round-off; ``tests/test_engines_agree.py`` checks that.

It is O(n^3) per scalar update: use it to check, not to run.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from v2v.estimation.filter import ClusterFilterBase
from v2v.estimation.models import Row, dense_row
from v2v.estimation.process import transition
from v2v.frames import wrap_angle


class ReferenceClusterEkf(ClusterFilterBase):
    """Dense filterpy implementation of :class:`v2v.estimation.filter.ClusterEkf`."""

    def _replace(self, x, P) -> None:
        n = self.layout.n
        self._ekf = ExtendedKalmanFilter(dim_x=n, dim_z=1)
        self._ekf.x = np.array(x, dtype=float).reshape(n, 1)
        self._ekf.P = np.array(P, dtype=float)

    def _get_x(self):
        return self._ekf.x[:, 0]

    def _get_P(self):
        return self._ekf.P

    def _predict_core(self, dt_s: float) -> None:
        self._ekf.F, self._ekf.Q = transition(self.layout, self.config.process, dt_s)
        self._ekf.predict()

    def _apply(self, row: Row, z: float, r_var: float, wrap: bool, test: bool) -> tuple[float, float, bool]:
        ekf = self._ekf
        h_mat = dense_row(row, self.layout.n)  # (1, n)
        r_mat = np.array([[r_var]])
        nu = float(wrap_angle(z - row.h)) if wrap else float(z - row.h)
        s = float((h_mat @ ekf.P @ h_mat.T + r_mat)[0, 0])
        if not (np.isfinite(nu) and np.isfinite(s) and s > 0.0):
            return nu, s, False
        if test and abs(nu) > self._k * np.sqrt(s):
            return nu, s, False

        def residual(z_col, hx_col):
            d = z_col - hx_col
            return wrap_angle(d) if wrap else d

        ekf.update(
            np.array([[z]]),
            HJacobian=lambda _x: h_mat,
            Hx=lambda _x: np.array([[row.h]]),
            R=r_mat,
            residual=residual,
        )
        return nu, s, True

    def _set_block(self, s: slice, mean, cov) -> None:
        ekf = self._ekf
        x = ekf.x.copy()
        P = ekf.P.copy()
        x[s, 0] = mean
        P[s, :] = 0.0
        P[:, s] = 0.0
        P[s, s] = cov
        ekf.x = x
        ekf.P = P
