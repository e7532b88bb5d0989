"""Parameter groups and their layout in the NLP.

A *group* is one physical quantity with a few components (a triad's gain, a pose's gravity
direction). Each component is free or fixed. Free components become decision variables ``x``
(divided by the group's scale, so IPOPT sees numbers of order one); fixed components go into the
NLP's parameter vector ``p``, so that changing them means re-solving, not rebuilding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


class Layout:
    """Maps groups onto the decision vector ``x`` and the fixed-value vector ``p``.

    Numeric bookkeeping only: free components become ``x`` (``value = x * scale``), fixed ones
    ``p_fixed`` (``value = p``). The solver gathers each group's values from the stacked vector
    ``w = [x * scale; p_fixed]`` with :meth:`w_index`. Build it once per problem structure; solve
    with other fixed values by passing another ``p``.
    """

    def __init__(self, groups: list[Group]):
        names = [g.name for g in groups]
        if len(set(names)) != len(names):
            raise ValueError("duplicate parameter group names")
        self.groups = list(groups)
        self._by_name = {g.name: g for g in groups}
        self.n_x = sum(int(g.free.sum()) for g in groups)
        self.n_p = sum(int((~g.free).sum()) for g in groups)
        self._w_index: dict[str, np.ndarray] = {}
        self.x_labels: list[str] = []
        ix, ip = 0, self.n_x
        for g in groups:
            w = np.empty(g.size, dtype=int)
            for c, is_free in enumerate(g.free):
                if is_free:
                    w[c] = ix
                    self.x_labels.append(f"{g.name}[{g.components[c]}]")
                    ix += 1
                else:
                    w[c] = ip
                    ip += 1
            self._w_index[g.name] = w

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def group(self, name: str) -> Group:
        return self._by_name[name]

    def w_index(self, name: str) -> np.ndarray:
        """Positions of a group's components in w = [x * scale; p_fixed]; < n_x means free."""
        return self._w_index[name]

    def x_indices(self, name: str) -> np.ndarray:
        """Positions in x of the free components of a group."""
        w = self._w_index[name]
        return w[w < self.n_x]

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
        w = np.concatenate([np.asarray(x, float).ravel() * self.x_scale, np.asarray(p, float).ravel()])
        return {g.name: w[self._w_index[g.name]] for g in self.groups}

    def priors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x index, mean, std) of every free component with a Gaussian prior."""
        idx, mean, std = [], [], []
        for g in self.groups:
            for c in np.flatnonzero(g.free & np.isfinite(g.prior_std)):
                idx.append(self._w_index[g.name][c])
                mean.append(g.prior_mean[c])
                std.append(g.prior_std[c])
        return np.array(idx, dtype=int), np.array(mean), np.array(std)

    def unit_norm_groups(self) -> list[Group]:
        """Groups constrained to |value|^2 = 1 that have a free component."""
        return [g for g in self.groups if g.unit_norm and g.free.any()]

    def check_start(self, x0: np.ndarray) -> list[str]:
        """Names of the free components whose initial value lies outside its bounds."""
        lo, hi = self.bounds()
        bad = np.flatnonzero((x0 < lo) | (x0 > hi))
        return [self.x_labels[i] for i in bad]
