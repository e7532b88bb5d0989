"""Parameter groups and their layout in the NLP.

A *group* is one physical quantity with a few components (a triad's gain, a pose's gravity
direction). Each component is free or fixed. Free components become decision variables ``x``
(divided by the group's scale, so IPOPT sees numbers of order one); fixed components go into the
NLP's parameter vector ``p``, so that changing them means re-solving, not rebuilding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


XYZ = ("x", "y", "z")


@dataclass(frozen=True)
class GroupDef:
    """Static description of a parameter group kind: components, neutral value, scale, unit, and the
    physical range of its components (``limits``; by default the neutral value ± RANGE_SCALES scales),
    outside which a value given in a problem file or an earlier results.json is refused."""

    components: tuple[str, ...]
    neutral: tuple[float, ...]
    scale: float
    unit: str
    unit_norm: bool = False
    limits: tuple[float, float] | None = None

    def physical_range(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) per component."""
        n = np.asarray(self.neutral, float)
        if self.limits is not None:
            return np.full(n.shape, float(self.limits[0])), np.full(n.shape, float(self.limits[1]))
        return n - RANGE_SCALES * self.scale, n + RANGE_SCALES * self.scale


#: Default physical range of a group's components, in units of its scale around the neutral value.
RANGE_SCALES = 1e4


@dataclass(frozen=True)
class Group:
    """One parameter group, all arrays in physical units and of shape (rows, components).

    A plain group (a triad's gain) has one row. A *matrix group* has one row per pose or sample
    (the gravity direction of every pose, ω of every sample), so that problems with many
    instances stay a handful of groups; factor blocks pick rows by index.

    Attributes
    ----------
    name
        Dotted name, e.g. ``imu2.accelerometer.gain`` or ``pose.direction``.
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
        Constrain |row|^2 = 1 (unit quaternions and unit vectors).
    nuisance
        A nuisance variable (pose direction, motion state): estimated, marginalised, not reported
        as a calibration parameter.
    matrix
        Rows are instances (values unpack to (rows, components)); else one row (unpacks to a vector).
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
    matrix: bool = False

    @staticmethod
    def make(name, components, initial, *, rows: int | None = None, free=True, lower=-np.inf, upper=np.inf,
             prior_mean=np.nan, prior_std=np.nan, scale=1.0, unit="-", unit_norm=False,
             nuisance=False) -> "Group":
        """A group; ``rows`` makes a matrix group (every argument broadcasts to (rows, components))."""
        shape = (rows or 1, len(components))

        def arr(v, dtype=float):
            return np.broadcast_to(np.asarray(v, dtype=dtype), shape).copy()

        return Group(name, tuple(components), arr(initial), arr(free, bool), arr(lower), arr(upper),
                     arr(prior_mean), arr(prior_std), arr(scale), unit, unit_norm, nuisance, rows is not None)

    @property
    def size(self) -> int:
        return len(self.components)

    @property
    def rows(self) -> int:
        return self.initial.shape[0]

    def shaped(self, v: np.ndarray) -> np.ndarray:
        """(rows, components) values as the user sees them: a vector for plain groups."""
        return v if self.matrix else v[0]


class Layout:
    """Maps groups onto the decision vector ``x`` and the fixed-value vector ``p``.

    Numeric bookkeeping only: free components become ``x`` (``value = x * scale``), fixed ones
    ``p_fixed`` (``value = p``), row by row. The solver gathers values from the stacked vector
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
        ix, ip = 0, self.n_x
        for g in groups:
            f = g.free.ravel()
            w = np.empty(f.size, dtype=int)
            w[f] = ix + np.arange(f.sum())
            w[~f] = ip + np.arange((~f).sum())
            ix, ip = ix + int(f.sum()), ip + int((~f).sum())
            self._w_index[g.name] = w.reshape(g.free.shape)

    @property
    def x_labels(self) -> list[str]:
        """A name per decision variable: ``group[component]`` or ``group[row][component]``."""
        out = []
        for g in self.groups:
            for r, c in zip(*np.nonzero(g.free)):
                out.append(f"{g.name}[{r}][{g.components[c]}]" if g.matrix else f"{g.name}[{g.components[c]}]")
        return out

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def group(self, name: str) -> Group:
        return self._by_name[name]

    def w_index(self, name: str) -> np.ndarray:
        """(rows, components) positions of a group in w = [x * scale; p_fixed]; < n_x means free."""
        return self._w_index[name]

    def x_indices(self, name: str) -> np.ndarray:
        """Positions in x of the free components of a group (row-major)."""
        w = self._w_index[name].ravel()
        return w[w < self.n_x]

    def _gather(self, attr: str, free: bool, values: dict | None = None) -> np.ndarray:
        parts = []
        for g in self.groups:
            v = getattr(g, attr) if values is None or g.name not in values else \
                np.broadcast_to(np.asarray(values[g.name], float), g.free.shape)
            parts.append(v[g.free if free else ~g.free])
        return np.concatenate(parts) if parts else np.zeros(0)

    @property
    def x_scale(self) -> np.ndarray:
        return self._gather("scale", True)

    def x0(self, initial: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Initial decision vector, from the groups' initial values or ``initial`` overrides."""
        return self._gather("initial", True, initial) / self.x_scale

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.x_scale
        return self._gather("lower", True) / s, self._gather("upper", True) / s

    def p0(self, values: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Fixed-value vector, from the groups' initial values or ``values`` overrides."""
        return self._gather("initial", False, values)

    def unpack(self, x: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
        """Physical values of every group from numeric x and p."""
        w = np.concatenate([np.asarray(x, float).ravel() * self.x_scale, np.asarray(p, float).ravel()])
        return {g.name: g.shaped(w[self._w_index[g.name]]) for g in self.groups}

    def priors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x index, mean, std) of every free component with a Gaussian prior."""
        idx, mean, std = [], [], []
        for g in self.groups:
            m = g.free & np.isfinite(g.prior_std)
            idx.append(self._w_index[g.name][m])
            mean.append(g.prior_mean[m])
            std.append(g.prior_std[m])
        cat = lambda a, t: np.concatenate(a).astype(t) if a else np.zeros(0, t)  # noqa: E731
        return cat(idx, int), cat(mean, float), cat(std, float)

    def unit_norm_rows(self) -> np.ndarray:
        """(n_constraints, components) w-positions of every unit-norm row with a free component.

        All unit-norm groups in one problem have the same number of components per kind; rows of
        different widths are padded with -1.
        """
        rows = [self._w_index[g.name][r] for g in self.groups if g.unit_norm
                for r in range(g.rows) if g.free[r].any()]
        if not rows:
            return np.zeros((0, 0), dtype=int)
        width = max(len(r) for r in rows)
        return np.array([np.pad(r, (0, width - len(r)), constant_values=-1) for r in rows], dtype=int)
