"""Parameter groups and their layout in the NLP.

A *group* is one physical quantity with a few components (a triad's gain, a pose's gravity
direction). Each component is free or fixed. Free components become decision variables ``x``
(divided by the group's scale, so IPOPT sees numbers of order one); fixed components go into the
NLP's parameter vector ``p``, so that changing them means re-solving, not rebuilding.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..models.rotation import quaternion_norm_residual


@dataclass(frozen=True)
class Group:
    """One parameter group, all arrays in physical units.

    Attributes
    ----------
    name
        Dotted name, e.g. ``imu2.accelerometer.gain`` or ``pose3.direction``.
    components
        Component labels, e.g. ``("x", "y", "z")``.
    initial, lower, upper
        Initial value and bounds per component (``-inf``/``inf`` where unbounded).
    free
        Which components are decision variables.
    prior_mean, prior_std
        Gaussian prior per component, ``nan`` std where there is none.
    scale
        Typical magnitude of a change; the decision variable is ``value / scale``.
    unit
        Physical unit, for reports.
    unit_norm
        Constrain |value|^2 = 1 (unit quaternions and unit vectors).
    nuisance
        A nuisance variable (pose direction, motion state): estimated, marginalised, not reported
        as a calibration parameter.
    """

    name: str
    components: tuple[str, ...]
    initial: np.ndarray
    free: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    prior_mean: np.ndarray
    prior_std: np.ndarray
    scale: np.ndarray
    unit: str = "-"
    unit_norm: bool = False
    nuisance: bool = False

    @staticmethod
    def make(name, components, initial, *, free=True, lower=-np.inf, upper=np.inf,
             prior_mean=np.nan, prior_std=np.nan, scale=1.0, unit="-", unit_norm=False,
             nuisance=False) -> "Group":
        n = len(components)

        def vec(v, dtype=float):
            return np.broadcast_to(np.asarray(v, dtype=dtype), (n,)).copy()

        return Group(name, tuple(components), vec(initial), vec(free, bool), vec(lower), vec(upper),
                     vec(prior_mean), vec(prior_std), vec(scale), unit, unit_norm, nuisance)

    @property
    def size(self) -> int:
        return len(self.components)


@dataclass
class Layout:
    """Maps groups onto the decision vector ``x`` and the fixed-value vector ``p``.

    Build it once per problem structure; solve with other fixed values by passing another ``p``.
    """

    groups: list[Group]
    sym: type = ca.SX
    x: ca.SX = field(init=False)
    p: ca.SX = field(init=False)
    _values: dict = field(init=False)
    x_labels: list[str] = field(init=False)

    def __post_init__(self):
        names = [g.name for g in self.groups]
        if len(set(names)) != len(names):
            raise ValueError("duplicate parameter group names")
        n_free = sum(int(g.free.sum()) for g in self.groups)
        n_fixed = sum(int((~g.free).sum()) for g in self.groups)
        self.x = self.sym.sym("x", n_free)
        self.p = self.sym.sym("p_fixed", n_fixed)
        self._values, self.x_labels = {}, []
        self._x_slices: dict[str, np.ndarray] = {}
        ix = ip = 0
        for g in self.groups:
            parts, xi = [], []
            for c, is_free in enumerate(g.free):
                if is_free:
                    parts.append(self.x[ix] * g.scale[c])
                    xi.append(ix)
                    self.x_labels.append(f"{g.name}[{g.components[c]}]")
                    ix += 1
                else:
                    parts.append(self.p[ip])
                    ip += 1
            self._values[g.name] = ca.vertcat(*parts)
            self._x_slices[g.name] = np.array(xi, dtype=int)
        self._by_name = {g.name: g for g in self.groups}

    # -- symbolic ----------------------------------------------------------------------------
    def value(self, name: str):
        """Symbolic physical value of a group (free parts from x, fixed parts from p)."""
        return self._values[name]

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def group(self, name: str) -> Group:
        return self._by_name[name]

    def prior_residuals(self):
        """Whitened prior residuals (value - mean) / std for every free component with a prior."""
        terms = []
        for g in self.groups:
            v = self._values[g.name]
            for c in np.flatnonzero(g.free & np.isfinite(g.prior_std)):
                terms.append((v[c] - g.prior_mean[c]) / g.prior_std[c])
        return ca.vertcat(*terms) if terms else self.sym(0, 1)

    def constraints(self):
        """Equality constraints (= 0): unit norm of quaternions and unit vectors with a free part."""
        terms = [quaternion_norm_residual(self._values[g.name])
                 for g in self.groups if g.unit_norm and g.free.any()]
        return ca.vertcat(*terms) if terms else self.sym(0, 1)

    # -- numeric -----------------------------------------------------------------------------
    def _gather(self, attr: str, free: bool) -> np.ndarray:
        parts = [getattr(g, attr)[g.free if free else ~g.free] for g in self.groups]
        return np.concatenate(parts) if parts else np.zeros(0)

    @property
    def x_scale(self) -> np.ndarray:
        return self._gather("scale", True)

    def x0(self, initial: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Initial decision vector, from the groups' initial values or ``initial`` overrides."""
        vals = []
        for g in self.groups:
            v = g.initial if initial is None or g.name not in initial else np.asarray(initial[g.name], float)
            vals.append(v[g.free] / g.scale[g.free])
        return np.concatenate(vals) if vals else np.zeros(0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.x_scale
        return self._gather("lower", True) / s, self._gather("upper", True) / s

    def p0(self, values: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Fixed-value vector, from the groups' initial values or ``values`` overrides."""
        vals = []
        for g in self.groups:
            v = g.initial if values is None or g.name not in values else np.asarray(values[g.name], float)
            vals.append(v[~g.free])
        return np.concatenate(vals) if vals else np.zeros(0)

    def unpack(self, x: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
        """Physical values of every group from numeric x and p."""
        x, p = np.asarray(x, float).ravel(), np.asarray(p, float).ravel()
        out, ix, ip = {}, 0, 0
        for g in self.groups:
            v = np.empty(g.size)
            nf = int(g.free.sum())
            v[g.free] = x[ix: ix + nf] * g.scale[g.free]
            v[~g.free] = p[ip: ip + g.size - nf]
            ix, ip = ix + nf, ip + g.size - nf
            out[g.name] = v
        return out

    def x_indices(self, name: str) -> np.ndarray:
        """Positions in x of the free components of a group."""
        return self._x_slices[name]

    def check_start(self, x0: np.ndarray) -> list[str]:
        """Names of the free components whose initial value lies outside its bounds."""
        lo, hi = self.bounds()
        bad = np.flatnonzero((x0 < lo) | (x0 > hi))
        return [self.x_labels[i] for i in bad]
