"""The dynamic array problem: motion states estimated jointly with the array geometry.

Carlsson, Skog, Jaldén 2017 (positions, with gyroscopes) and Schopp et al. 2016 (full poses,
accelerometers only), composed from the same blocks as the static problem::

    accelerometer triad k, sample n:  y = K L M Rbar (s_n + ω_n×(ω_n×r_k) + ω̇_n×r_k) + b + v
    gyroscope triad g, sample n:      y = K_g M_g Rbar ω_n + b_g + v
    process model n -> n+1:           ω̇ a Wiener process and ω its integral, s a random walk (exact
                                      discretisation); or Schopp's Euler step (eq. 7, 8) or the trapezoid rule

The reference triad is fixed at the origin with no misalignment: it defines the body frame.
Motion states are matrix groups (one row per sample), marginalised in the covariance.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import casadi as ca
import numpy as np

from ..jit import compiled
from ..models import motion as mot
from ..models import triad as tri
from .graph import FactorBlock, LeastSquaresProblem
from .parameters import Group, Layout
from . import effects as fxs
from .compensation import linear_inverse
from .parameters import XYZ
from .triads import (ACC_FACTOR_GROUPS, GYRO_FACTOR_GROUPS, N_SAMPLE_REGRESSORS, GroupSetting, Regressors, TriadConfig,
                     accelerometer_matrix, board_groups, effect_context, effect_params, group_name, gyroscope_matrix,
                     triad_groups)

OMEGA, OMEGA_DOT, S = "motion.omega", "motion.omega_dot", "motion.s"
OMEGA_DDOT = "motion.omega_ddot"  # a state of the wiener3 process model only


#: Schopp 2016, eq. 8: σ_a² = 1e3 (m/s²)², σ_ω̇² = 1e3 (rad/s²)², σ_int² = 1e-7 (rad/s)².
SCHOPP_SIGMAS = {"s": 1e3 ** 0.5, "omega_dot": 1e3 ** 0.5, "omega": 1e-7 ** 0.5}
#: Start levels of the Wiener models (√q_s [m/s^2.5], √q_ω [rad/s^2.5 (wiener2) or rad/s^3.5 (wiener3)]),
#: re-estimated from the data by default (hand-held motion: √q_ω of a few hundred to a few thousand).
WIENER_START = {"wiener2": {"s": 5.0, "omega_dot": 30.0, "omega": 30.0},
                "wiener3": {"s": 5.0, "omega_dot": 300.0, "omega": 300.0}}


@dataclass(frozen=True)
class MotionSigmas:
    """The process model between consecutive samples (``models.motion``).

    ``integration``: ``wiener3`` (default; ω̈ a Wiener process, i.e. white angular snap, with ω̇
    and ω its exact integrals: ``process_residual_snap``), ``wiener2`` (ω̇ a Wiener process: white
    angular jerk), ``trapezoid`` or ``euler`` (Schopp 2016, eq. 7, with Schopp's σ's, eq. 8); s is
    a random walk in all. ``s``, ``omega`` and ``omega_dot`` are the levels of the s, ω and ω̇ rows
    (Wiener: √q_s, and ``omega`` = ``omega_dot`` = √q_ω of the ω chain); None takes the
    integration's defaults. ``estimate``: re-estimate the levels from the data (variance
    components, ``solver.variance``), starting from these.
    """

    integration: str = "wiener3"
    s: float | None = None  # m/s^2 (euler, trapezoid) or m/s^2.5 (Wiener)
    omega_dot: float | None = None  # rad/s^2 (euler, trapezoid), rad/s^2.5 (wiener2) or rad/s^3.5 (wiener3)
    omega: float | None = None  # rad/s, σ_int (euler, trapezoid); = omega_dot (Wiener)
    estimate: bool = True

    def __post_init__(self):
        if self.integration not in mot.INTEGRATIONS:
            raise ValueError(f"unknown integration {self.integration!r}; expected one of {mot.INTEGRATIONS}")
        dflt = WIENER_START[self.integration] if self.wiener else SCHOPP_SIGMAS
        for k in ("s", "omega_dot", "omega"):
            if getattr(self, k) is None:
                object.__setattr__(self, k, dflt[k])
        if self.wiener and self.omega != self.omega_dot:
            object.__setattr__(self, "omega", self.omega_dot)

    @property
    def wiener(self) -> bool:
        return self.integration.startswith("wiener")

    @property
    def components(self) -> dict[str, tuple[int, ...]]:
        """Variance components: name -> rows of the process residual (s, then the ω rows) they scale."""
        if self.wiener:
            return {"s": (0, 1, 2), "omega_dot": tuple(range(3, 12 if self.integration == "wiener3" else 9))}
        return {"s": (0, 1, 2), "omega": (3, 4, 5), "omega_dot": (6, 7, 8)}

    @property
    def units(self) -> dict[str, str]:
        if self.wiener:
            return {"s": "m/s^2.5", "omega_dot": "rad/s^3.5" if self.integration == "wiener3" else "rad/s^2.5"}
        return {"s": "m/s^2", "omega": "rad/s", "omega_dot": "rad/s^2"}

    def levels(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.components}

    def with_levels(self, levels: dict[str, float]) -> MotionSigmas:
        out = replace(self, **levels)
        return replace(out, omega=out.omega_dot) if self.wiener else out


@dataclass(frozen=True)
class DynamicConfig:
    """The structure of a dynamic array problem."""

    triads: tuple[TriadConfig, ...]
    reference: str
    misalignment: str = "small_angle"  # small_angle | rotation (Schopp's full orientation)
    motion: MotionSigmas = MotionSigmas()
    process_model: bool = True
    effects: tuple[str, ...] = ()  # included effects (problem.effects)
    regressors: Regressors | None = None  # time and temperature references of the effects
    age_order: int = 1  # Taylor order of the timing effects' sample age (model.sample_age): 1 or 2

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.triads]


@dataclass(frozen=True)
class DynamicData:
    """A motion recording in SI units with validity per sample and axis (saturation masks).

    ``acc_sigma``/``gyro_sigma`` are per-sample white-noise σ per axis, (3,). ``acc_valid``/``gyro_valid``
    per triad: (N, 3) which axes read (an ADC clips each channel on its own), or (N,) per sample.
    ``sigma_sample`` ("acc"
    | "gyro" -> triad -> (N, 3)) replaces them sample by sample where a motion-dependent noise model
    is fitted (:mod:`castimate.solver.motion_noise`); :meth:`sigma` gives the σ in effect.
    """

    t: np.ndarray
    acc: dict[str, np.ndarray]
    acc_sigma: dict[str, np.ndarray]
    gyro: dict[str, np.ndarray] = field(default_factory=dict)
    gyro_sigma: dict[str, np.ndarray] = field(default_factory=dict)
    acc_valid: dict[str, np.ndarray] = field(default_factory=dict)
    gyro_valid: dict[str, np.ndarray] = field(default_factory=dict)
    temp: dict[str, np.ndarray] = field(default_factory=dict)  # K, where logged
    sigma_sample: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.t)

    def sigma(self, kind: str, name: str) -> np.ndarray:
        """(N, 3) σ of triad ``name``'s ``kind`` ("acc" | "gyro") readings, sample by sample."""
        s = self.sigma_sample.get(kind, {}).get(name)
        if s is not None:
            return s
        return np.broadcast_to((self.acc_sigma if kind == "acc" else self.gyro_sigma)[name], (self.n, 3))

    def take(self, idx) -> "DynamicData":
        """The samples ``idx`` only (e.g. a cross-validation fold)."""
        idx = np.asarray(idx)
        pick = lambda d: {k: v[idx] for k, v in d.items()}  # noqa: E731
        return replace(self, t=self.t[idx], acc=pick(self.acc), gyro=pick(self.gyro), acc_valid=pick(self.acc_valid),
                       gyro_valid=pick(self.gyro_valid), temp=pick(self.temp),
                       sigma_sample={k: pick(v) for k, v in self.sigma_sample.items()})

    def window(self, start: int, n: int) -> "DynamicData":
        """Samples start .. start + n - 1 (a fixed-size window, e.g. for the C solver)."""
        return self.take(np.arange(self.n)[start:start + n])

    def axis_valid(self, kind: str, name: str) -> np.ndarray:
        """(N, 3) the axes of a triad's readings that count (not on a rail)."""
        m = (self.acc_valid if kind == "acc" else self.gyro_valid).get(name)
        if m is None:
            return np.ones((self.n, 3), bool)
        return np.broadcast_to(m[:, None], (self.n, 3)) if m.ndim == 1 else m

    def valid(self, kind: str, name: str) -> np.ndarray:
        """(N,) the samples where any axis of a triad's reading counts: its instances in the problem."""
        if (self.acc_valid if kind == "acc" else self.gyro_valid).get(name) is None:  # every sample (no (N, 3) to reduce)
            return np.ones(self.n, bool)
        return self.axis_valid(kind, name).any(axis=1)


def accelerometer_sample_factor(config: DynamicConfig) -> ca.Function:
    """Whitened residual of one accelerometer triad at one sample (DESIGN.md triad model with the
    rigid-body specific force, Carlsson 2017 eq. 1), plus the included effects' terms.

    z = [k, l, m, b, r, ω, ω̇, s, effect parameters..., (ω̇, s) of samples n-1 and n+1 if an effect
    acts on the reading's rate], d = [y, σ, vec(Rbar), τ, τ², ΔT, ΔT², beat, 1/(t_n+1 - t_n-1),
    4/(t_n+1 - t_n-1)² (0 at the ends)]. The rate is T ḟ (``models.motion.specific_force_rate``) with ṡ
    and ω̈ as central differences; its rate T f̈ (``models.motion.specific_force_acceleration``, the sample age's second-order term) with s̈ and ω⃛ as
    central second differences (a uniform grid assumed; dropped at the first and last samples).
    """
    Tfn = accelerometer_matrix(config.misalignment)
    effects = fxs.acting_on(config.effects, "accelerometer")
    k, l, m, b = ca.SX.sym("k", 3), ca.SX.sym("l", 3), ca.SX.sym("m", Tfn.size1_in(2)), ca.SX.sym("b", 3)
    r, w, wd, s = ca.SX.sym("r", 3), ca.SX.sym("omega", 3), ca.SX.sym("omega_dot", 3), ca.SX.sym("s", 3)
    y, sigma, R = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9)
    reg, inv_span, inv_h2 = ca.SX.sym("regressors", N_SAMPLE_REGRESSORS), ca.SX.sym("inv_span"), ca.SX.sym("inv_h2")
    c = effect_params(effects)
    T = Tfn(k, l, m, ca.reshape(R, 3, 3))
    f = mot.specific_force_at(s, w, wd, r)
    z = [k, l, m, b, r, w, wd, s, *c]
    u_dot = u_ddot = None
    if fxs.need(effects, fxs.RATE):
        prev, nxt = [ca.SX.sym(n, 6) for n in ("motion_prev", "motion_next")]  # (ω̇, s)
        z += [prev, nxt]
        u_dot = accelerometer_rate()(T, r, w, wd, prev, nxt, inv_span)
        if config.age_order == 2:
            u_ddot = accelerometer_rate_of_rate()(T, r, w, wd, s, prev, nxt, inv_span, inv_h2)
    ctx = effect_context(reg, u=ca.mtimes(T, f), T=T, omega=w, omega_dot=wd, u_dot=u_dot, u_ddot=u_ddot,
                         Rbar=ca.reshape(R, 3, 3))
    res = (y - tri.triad_output(T, b, f) - fxs.total(effects, c, ctx)) / sigma
    return ca.Function("accelerometer_sample", [ca.vertcat(*z), ca.vertcat(y, sigma, R, reg, inv_span, inv_h2)], [res])


def accelerometer_rate() -> ca.Function:
    """u̇ = T ḟ of an accelerometer triad at sample n (``models.motion.specific_force_rate``), with ṡ
    and ω̈ as central differences of the neighbouring samples' (ω̇, s): (T, r, ω, ω̇, (ω̇, s)_n-1,
    (ω̇, s)_n+1, 1/(t_n+1 - t_n-1)) -> u̇."""
    T, r, w, wd = ca.SX.sym("T", 3, 3), ca.SX.sym("r", 3), ca.SX.sym("omega", 3), ca.SX.sym("omega_dot", 3)
    prev, nxt, inv_span = ca.SX.sym("prev", 6), ca.SX.sym("next", 6), ca.SX.sym("inv_span")
    f_dot = mot.specific_force_rate((nxt[3:6] - prev[3:6]) * inv_span, w, wd, (nxt[0:3] - prev[0:3]) * inv_span, r)
    return ca.Function("accelerometer_rate", [T, r, w, wd, prev, nxt, inv_span], [ca.mtimes(T, f_dot)])


@functools.lru_cache(maxsize=2)
def _rate_function(jit: bool) -> ca.Function:
    """:func:`accelerometer_rate`, built once, with ``jit`` compiled to C (:mod:`castimate.jit`, the
    same results; 1.5 x faster over MIMU4444 exp_1's samples) where a compiler is at hand."""
    f = accelerometer_rate()
    return compiled({"rate": f}, None, jit).result()["rate"]


def accelerometer_rate_of_rate() -> ca.Function:
    """ü = T f̈ of an accelerometer triad at sample n (``models.motion.specific_force_acceleration``):
    ω̈ the central difference of the neighbours' ω̇, s̈ and ω⃛ the central second differences of (s, ω̇)
    (``inv_h2`` = 4/(t_n+1 - t_n-1)², 0 where there are no neighbours on both sides): (T, r, ω, ω̇, s,
    (ω̇, s)_n-1, (ω̇, s)_n+1, 1/(t_n+1 - t_n-1), inv_h2) -> ü."""
    T, r, w, wd, s = (ca.SX.sym("T", 3, 3), ca.SX.sym("r", 3), ca.SX.sym("omega", 3), ca.SX.sym("omega_dot", 3),
                      ca.SX.sym("s", 3))
    prev, nxt, inv_span, inv_h2 = ca.SX.sym("prev", 6), ca.SX.sym("next", 6), ca.SX.sym("inv_span"), ca.SX.sym("inv_h2")
    second = lambda i, x: (nxt[i:i + 3] - 2 * x + prev[i:i + 3]) * inv_h2  # noqa: E731
    f_ddot = mot.specific_force_acceleration(second(3, s), w, wd, (nxt[0:3] - prev[0:3]) * inv_span, second(0, wd), r)
    return ca.Function("accelerometer_rate_of_rate", [T, r, w, wd, s, prev, nxt, inv_span, inv_h2],
                       [ca.mtimes(T, f_ddot)])


def _gyro_needs(effects: list[fxs.Effect], age_order: int = 1) -> tuple[bool, bool, bool]:
    """(ω̇, specific force, the neighbours' ω̇): the motion a gyroscope factor's effects need beyond ω
    (the neighbours' ω̇ for ω̈ of a second-order sample age)."""
    force, rate = fxs.need(effects, fxs.SPECIFIC_FORCE), fxs.need(effects, fxs.RATE)
    return force or rate, force, rate and age_order == 2


def gyroscope_sample_factor(config: DynamicConfig) -> ca.Function:
    """Whitened residual of one gyroscope triad at one sample: y = T_g ω + b_g (Carlsson 2017, eq. 2,
    with the DESIGN.md gyroscope model), plus the included effects' terms (and the shared chip
    effects of the triad, ``Effect.shared``).

    z = [k_g, m_g, b_g, ω, ω̇ if an effect needs it, (r, s) if g-sensitivity is included, effect
    parameters...], d as for the accelerometers. The reading's rate is T_g ω̇.
    """
    effects = fxs.acting_on(config.effects, "gyroscope")
    k, m, b, w = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("b", 3), ca.SX.sym("omega", 3)
    y, sigma, R = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9)
    reg, inv_span, inv_h2 = ca.SX.sym("regressors", N_SAMPLE_REGRESSORS), ca.SX.sym("inv_span"), ca.SX.sym("inv_h2")
    Rbar = ca.reshape(R, 3, 3)
    T = gyroscope_matrix()(k, m, Rbar)
    z, f, u_dot, u_ddot = [k, m, b, w], None, None, None
    need_wd, need_f, need_rate = _gyro_needs(effects, config.age_order)
    wd = ca.SX.sym("omega_dot", 3)
    if need_wd:
        z.append(wd)
        u_dot = ca.mtimes(T, wd)
    if need_f:
        r, s = ca.SX.sym("r", 3), ca.SX.sym("s", 3)
        z += [r, s]
        f = ca.mtimes(Rbar, mot.specific_force_at(s, w, wd, r))
    c = effect_params(effects)
    z += c
    if need_rate:  # the reading's rate of rate T ω̈, ω̈ the central difference of the neighbours' ω̇
        prev, nxt = ca.SX.sym("omega_dot_prev", 3), ca.SX.sym("omega_dot_next", 3)
        z += [prev, nxt]
        u_ddot = ca.mtimes(T, (nxt - prev) * inv_span)
    ctx = effect_context(reg, u=ca.mtimes(T, w), f=f, u_dot=u_dot, u_ddot=u_ddot)
    res = (y - tri.triad_output(T, b, w) - fxs.total(effects, c, ctx)) / sigma
    return ca.Function("gyroscope_sample", [ca.vertcat(*z), ca.vertcat(y, sigma, R, reg, inv_span, inv_h2)], [res])


def process_factor(integration: str = "wiener3") -> ca.Function:
    """Whitened process-model residual between consecutive samples (``models.motion.process_residual``;
    Schopp 2016, eq. 14, for ``euler``). z = [ω_n, ω̇_n, s_n, ω_n+1, ω̇_n+1, s_n+1 (, ω̈_n, ω̈_n+1 for
    wiener3)], d = [Δt, σ_s, σ_ω, σ_ω̇] (the levels of ``MotionSigmas``)."""
    z = [ca.SX.sym(n, 3) for n in ("omega", "omega_dot", "s", "omega_next", "omega_dot_next", "s_next")]
    d = ca.SX.sym("d", 4)
    if integration == "wiener3":
        wdd = [ca.SX.sym(n, 3) for n in ("omega_ddot", "omega_ddot_next")]
        res = mot.process_residual_snap(z[0], z[1], wdd[0], z[2], z[3], z[4], wdd[1], z[5], d[0], d[1], d[3])
        z += wdd
    else:
        res = mot.process_residual(*z, d[0], d[1], d[2], d[3], integration)
    return ca.Function("process_model", [ca.vertcat(*z), d], [res])


def position_group(config: DynamicConfig, t: TriadConfig) -> Group:
    """The triad's position (body frame, m); fixed at the origin for the reference triad."""
    ref = next(x for x in config.triads if x.name == config.reference)
    nominal = np.zeros(3) if t.position is None else t.position - (ref.position if ref.position is not None else 0)
    s = t.position_setting or GroupSetting(free=(True,) * 3)
    if t.name == config.reference:
        s = GroupSetting(free=(False,) * 3)
        nominal = np.zeros(3)
    return Group.make(f"{t.name}.position", XYZ, nominal if s.initial is None else s.initial,
                      free=s.free, lower=-np.inf if s.lower is None else s.lower,
                      upper=np.inf if s.upper is None else s.upper,
                      prior_mean=np.nan if s.prior_mean is None else s.prior_mean,
                      prior_std=np.nan if s.prior_std is None else s.prior_std, scale=1e-3, unit="m")


def geometry_fixed(config: DynamicConfig) -> DynamicConfig:
    """The same array with every triad's intrinsics and position fixed at their start values: the
    problem is then the array's per-sample maximum-likelihood motion estimator (Carlsson 2017,
    sec. III, the ω, ω̇, s step of Algorithm 1 for a known geometry)."""
    def fix(s: GroupSetting | None, n: int = 3) -> GroupSetting:
        s = s or GroupSetting(free=(True,) * n)
        return replace(s, free=(False,) * len(s.free))

    triads = tuple(replace(t, accelerometer={g: fix(v) for g, v in t.accelerometer.items()},
                           gyroscope=None if t.gyroscope is None else {g: fix(v) for g, v in t.gyroscope.items()},
                           position_setting=fix(t.position_setting)) for t in config.triads)
    return replace(config, triads=triads)


@dataclass
class DynamicProblem:
    config: DynamicConfig
    lsq: LeastSquaresProblem
    n_samples: int
    gyro_triads: list[str]
    rows: dict  # "acc" | "gyro" -> triad name -> indices of the valid samples
    axes: dict = None  # "acc" | "gyro" -> triad name -> (N, 3) the axes that count (all where absent)

    def valid(self, kind: str, names) -> np.ndarray:
        """(N, K): which (sample, triad) instances of a sensor block are valid readings."""
        return _valid(self.rows[kind], names, self.n_samples)

    def valid_axes(self, kind: str, names) -> np.ndarray:
        """(N, K, 3): which axes of the valid instances count; a clipped axis of a valid instance is weighted
        out by σ = MASKED_SIGMA."""
        ax = (self.axes or {}).get(kind, {})
        return self.valid(kind, names)[..., None] & np.stack(
            [ax.get(n, np.ones((self.n_samples, 3), bool)) for n in names], axis=1)

    def block_data(self, data: DynamicData) -> list[np.ndarray]:
        """Data of every block in problem order (accelerometers, gyroscopes, process model). Sensor
        blocks are sample-major over every triad; a masked sample gets y = 0 and σ = inf, so its
        residual and derivatives are exactly zero (its block instance is not ``valid``); a masked axis
        of a valid sample gets y = 0 and σ = MASKED_SIGMA (left out of the residuals and the dof)."""
        R = {t.name: t.R_nominal for t in self.config.triads}

        reg = self.config.regressors or Regressors.from_times(data.t, data.temp)
        prev, nxt = _neighbours(data.n)
        inv_span = 1.0 / (data.t[nxt] - data.t[prev]) if data.n > 1 else np.zeros(data.n)
        inv_h2 = np.where(nxt - prev == 2, 4.0 * inv_span ** 2, 0.0)  # central second differences (none at the ends)

        def stack(names, kind, y):
            # sample-major (n, k) rows, filled a slab of samples at a time: each triad's columns are
            # written into a small triad-major array (contiguous, in cache), which is then copied
            # transposed into the slab of the result. Writing the triads' columns into the result
            # directly strides over it (one page per row at 32 triads) and took 0.37 s at
            # 32 triads x 20 000 samples (the result is 118 MB)
            K, C = len(names), 17 + N_SAMPLE_REGRESSORS
            ok = self.valid(kind, names)
            ax = (self.axes or {}).get(kind, {})
            Rcols = np.stack([R[n].ravel(order="F") for n in names])
            sig = [data.sigma(kind, n) for n in names]
            moments = [reg.sample_moments(data.t, data.temp.get(n), n) for n in names]
            out = np.empty((self.n_samples, K, C))
            tmp = np.empty((K, SLAB, C))
            for s0 in range(0, self.n_samples, SLAB):
                s1 = min(self.n_samples, s0 + SLAB)
                t = tmp[:, : s1 - s0]
                for k, n in enumerate(names):
                    t[k, :, 0:3] = y[n][s0:s1]
                    t[k, :, 3:6] = sig[k][s0:s1]
                    t[k, :, 15: 15 + N_SAMPLE_REGRESSORS] = moments[k][s0:s1]
                t[:, :, 6:15] = Rcols[:, None, :]
                t[:, :, 15 + N_SAMPLE_REGRESSORS] = inv_span[None, s0:s1]
                t[:, :, 16 + N_SAMPLE_REGRESSORS] = inv_h2[None, s0:s1]
                out[s0:s1] = t.transpose(1, 0, 2)
            if not ok.all() or not all(ax[n].all() for n in names if n in ax):  # some axis masked
                axes = ok[..., None] & np.stack([ax.get(n, np.ones((self.n_samples, 3), bool)) for n in names], axis=1)
                out[:, :, 0:3][~axes] = 0.0
                out[:, :, 3:6] = np.where(axes, out[:, :, 3:6], np.where(ok[..., None], MASKED_SIGMA, np.inf))
            return out.reshape(-1, C)

        out = [stack(self.config.names, "acc", data.acc)]
        if self.gyro_triads:
            out.append(stack(self.gyro_triads, "gyro", data.gyro))
        if self.config.process_model:
            m = self.config.motion
            dt = np.diff(data.t)
            out.append(np.column_stack([dt, np.full_like(dt, m.s), np.full_like(dt, m.omega),
                                        np.full_like(dt, m.omega_dot)]))
        return out

    def reading_rates(self, values: dict, data: DynamicData, jit: bool = False) -> tuple[dict, dict]:
        """u̇ of every triad and sample at the fitted ``values``, (N, 3) per triad: T ḟ of the
        accelerometers (:func:`accelerometer_rate`, compiled with ``jit``) and T_g ω̇ of the gyroscopes,
        as in the factors of effects acting on the rate."""
        prev, nxt = _neighbours(data.n)
        wd, s = values[OMEGA_DOT], values[S]
        inv_span = 1.0 / (data.t[nxt] - data.t[prev]) if data.n > 1 else np.zeros(data.n)
        # one call per triad over all samples (T and r shared: CasADi's MapSum), in place: the
        # motion's (N, k) rows are the columns of CasADi's column-major (k, N) inputs
        buf, run = _rate_function(jit).map(data.n, [True, True] + [False] * 5, [False]).buffer()
        motion = [np.ascontiguousarray(a, float) for a in (values[OMEGA], wd, np.hstack([wd[prev], s[prev]]),
                                                           np.hstack([wd[nxt], s[nxt]]), inv_span)]
        for i, a in enumerate(motion, start=2):
            buf.set_arg(i, memoryview(a))
        acc = {}
        for n, (T, _) in self.calibration(values).items():
            Tc = np.asarray(T, float).ravel(order="F")  # column-major, as CasADi stores a 3 x 3
            r = np.ascontiguousarray(values[f"{n}.position"], float)
            acc[n] = np.empty((data.n, 3))
            for i, a in enumerate((Tc, r)):
                buf.set_arg(i, memoryview(a))
            buf.set_res(0, memoryview(acc[n]))
            run()
        gyro = {n: wd @ T.T for n, (T, _) in self.gyro_calibration(values).items()}
        return acc, gyro

    def data_vector(self, data: DynamicData) -> np.ndarray:
        """The data of every block for ``data`` (blocks beyond the dynamic ones, the static poses
        of a joint problem, keep theirs)."""
        blocks = self.block_data(data)
        return self.lsq.pack(blocks + [b.data for b in self.lsq.blocks[len(blocks):]])

    def per_triad(self, v: np.ndarray) -> tuple[dict, dict]:
        """A vector over the data residuals (the valid axes, sample-major over the triads, the
        accelerometers first) as (N, 3) per triad, NaN where an axis is masked: (accelerometers,
        gyroscopes)."""
        out_a, out_g, off = {}, {}, 0
        for kind, names, out in (("acc", self.config.names, out_a), ("gyro", self.gyro_triads, out_g)):
            if not names:
                continue
            ok = self.valid_axes(kind, names)  # (N, K, 3)
            full = np.full((self.n_samples, len(names), 3), np.nan)
            full[ok] = v[off: off + int(ok.sum())]
            off += int(ok.sum())
            out.update({n: full[:, i] for i, n in enumerate(names)})
        return out_a, out_g

    def calibration(self, values: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """(T, b) of every accelerometer triad: raw = T f + b with f in the body frame."""
        Tfn = accelerometer_matrix(self.config.misalignment)
        v = lambda n, g: values[group_name(n, "accelerometer", g)]  # noqa: E731
        return {t.name: (np.asarray(Tfn(v(t.name, "gain"), v(t.name, "nonorthogonality"), v(t.name, "misalignment"),
                                        t.R_nominal)), v(t.name, "bias")) for t in self.config.triads}

    def gyro_calibration(self, values: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        Tfn = gyroscope_matrix()
        R = {t.name: t.R_nominal for t in self.config.triads}
        v = lambda n, g: values[group_name(n, "gyroscope", g)]  # noqa: E731
        return {n: (np.asarray(Tfn(v(n, "gain"), v(n, "misalignment"), R[n])), v(n, "bias")) for n in self.gyro_triads}


def _start_value(setting, group: str, default):
    """A triad's group start: the problem's ``initial`` where given, else ``default``."""
    return setting[group].initial if setting[group].initial is not None else default


def _start_specific_force(config: DynamicConfig, t: TriadConfig, data: DynamicData) -> np.ndarray:
    """(N, 3) triad ``t``'s readings compensated with its start intrinsics: the specific force in the body frame."""
    a = lambda g, d: _start_value(t.accelerometer, g, d)  # noqa: E731
    T = accelerometer_matrix(config.misalignment)(a("gain", [1, 1, 1]), a("nonorthogonality", [0, 0, 0]),
                                                   [1, 0, 0, 0] if config.misalignment == "rotation" else [0, 0, 0],
                                                   t.R_nominal)
    return linear_inverse(T, np.asarray(a("bias", [0, 0, 0]), float), data.acc[t.name])


def initial_motion(config: DynamicConfig, data: DynamicData, gyro_triads: list[str]) -> dict[str, np.ndarray]:
    """Start of the motion states (Schopp 2016, sec. VI-B, and gyro-aided when gyros exist).

    s: the reference triad's compensated reading (it sits at the origin, so it measures s).
    ω: the mean compensated gyroscope reading, interpolated over saturated samples. Without gyros,
    ω and ω̇ from the array itself (:func:`castimate.models.motion.angular_motion_from_specific_forces`
    on the start poses, signs by continuity with ∫ω̇): a zero start is a flat point of the centripetal
    terms, from which the solver may not leave at high rates. ω̇: the derivative of the gyro-aided ω.
    """
    ref = next(t for t in config.triads if t.name == config.reference)
    s = _start_specific_force(config, ref, data)
    omega = np.zeros((data.n, 3))
    if not gyro_triads and data.n > 1:
        r = np.stack([position_group(config, t).initial.reshape(3) for t in config.triads])
        f = np.stack([_start_specific_force(config, t, data) for t in config.triads], axis=1)
        valid = np.stack([data.axis_valid("acc", t.name) for t in config.triads], axis=1)
        omega, omega_dot, _, _ = mot.angular_motion_from_specific_forces(data.t, f, r, valid)
        return {OMEGA: omega, OMEGA_DOT: omega_dot, S: s}
    if gyro_triads:
        est, weight = np.zeros((data.n, 3)), np.zeros(data.n)
        Tfn = gyroscope_matrix()  # one CasADi function for every triad (1 ms to build)
        for name in gyro_triads:
            t = next(t for t in config.triads if t.name == name)
            Tg = Tfn(_start_value(t.gyroscope, "gain", [1, 1, 1]), _start_value(t.gyroscope, "misalignment", [0, 0, 0]),
                     t.R_nominal)
            w = linear_inverse(Tg, np.asarray(_start_value(t.gyroscope, "bias", [0, 0, 0]), float), data.gyro[name])
            ok = data.axis_valid("gyro", name).all(axis=1)  # a clipped axis leaks into the others through T_g
            # the valid samples' sums, in place (boolean indexing copied both sides: 1.4 ms per triad)
            np.add(est, w, out=est, where=ok[:, None])
            weight += ok
        good = weight > 0
        if good.any():
            omega = np.column_stack([np.interp(data.t, data.t[good], est[good, i] / weight[good]) for i in range(3)])
    omega_dot = np.gradient(omega, data.t, axis=0) if data.n > 1 else np.zeros_like(omega)
    return {OMEGA: omega, OMEGA_DOT: omega_dot, S: s}


SLAB = 512  # samples per slab of DynamicProblem.block_data
#: The sensor factors' data columns of vec(R̄), the triad's nominal rotation (DynamicProblem.block_data):
#: the same for every sample of a triad (FactorBlock.shared_data)
R_COLUMNS = tuple(range(6, 15))


def _valid(rows: dict, names, N: int) -> np.ndarray:
    """(N, K) from the valid sample indices of each triad (sample indices, as from np.flatnonzero:
    set by index, 0.02 ms per triad at 20 000 samples where np.isin sorted them, 0.3 ms)."""
    out = np.zeros((N, len(names)), bool)
    for k, n in enumerate(names):
        out[rows[n], k] = True
    return out


def _neighbours(N: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the samples before and after each sample, clamped at the ends (one-sided there)."""
    i = np.arange(N)
    return np.maximum(i - 1, 0), np.minimum(i + 1, N - 1)


def _gyro_triads(config: DynamicConfig, data: DynamicData) -> list[str]:
    return [t.name for t in config.triads if t.gyroscope is not None and t.name in data.gyro]


def build_dynamic(config: DynamicConfig, data: DynamicData, start: dict | None = None) -> DynamicProblem:
    """Compose the dynamic problem; data and fixed values are NLP parameters."""
    N = data.n
    gyro_triads = _gyro_triads(config, data)
    start = {**initial_motion(config, data, gyro_triads), **(start or {})}
    groups = []
    for t in config.triads:
        groups += triad_groups(config, t, t.name in gyro_triads)
        groups.append(position_group(config, t))
    groups += board_groups(config)
    groups += [Group.make(OMEGA, XYZ, start[OMEGA], rows=N, unit="rad/s", nuisance=True),
               Group.make(OMEGA_DOT, XYZ, start[OMEGA_DOT], rows=N, scale=10.0, unit="rad/s^2", nuisance=True),
               Group.make(S, XYZ, start[S], rows=N, unit="m/s^2", nuisance=True)]
    snap = config.process_model and config.motion.integration == "wiener3"
    if snap:
        wdd = start.get(OMEGA_DDOT, np.gradient(start[OMEGA_DOT], data.t, axis=0) if N > 1 else np.zeros((N, 3)))
        groups.append(Group.make(OMEGA_DDOT, XYZ, wdd, rows=N, scale=100.0, unit="rad/s^3", nuisance=True))
    rows = {"acc": {n: np.flatnonzero(data.valid("acc", n)) for n in config.names},
            "gyro": {n: np.flatnonzero(data.valid("gyro", n)) for n in gyro_triads}}
    axes = {"acc": {n: data.axis_valid("acc", n) for n in config.names},
            "gyro": {n: data.axis_valid("gyro", n) for n in gyro_triads}}

    def instances(kind, names):  # (triad index, sample index) of every instance, sample-major; which axes count
        k, n = np.tile(np.arange(len(names)), N), np.repeat(np.arange(N), len(names))
        return k, n, (_valid(rows[kind], names, N)[..., None] & np.stack([axes[kind][m] for m in names], 1)).reshape(-1, 3)

    if config.regressors is None:
        config = replace(config, regressors=Regressors.from_times(data.t, data.temp))
    prev, nxt = _neighbours(N)

    def effect_inputs(sensor, names, k):  # a board effect's one group feeds every instance (rows None)
        return [(fxs.group_names(e, ())[0], None) if e.board else (tuple(fxs.group_names(e, names)), k)
                for e in fxs.acting_on(config.effects, sensor)]

    # One instance per (sample, triad), sample-major and including masked samples (zero residual,
    # not valid): the Solver assembles such blocks sample by sample (see solve.py, "Stages").
    k, n, ok = instances("acc", config.names)
    effects = fxs.acting_on(config.effects, "accelerometer")
    blocks = [FactorBlock("accelerometer_sample", accelerometer_sample_factor(config),
                          [(tuple(group_name(t, "accelerometer", g) for t in config.names), k) for g in ACC_FACTOR_GROUPS]
                          + [(tuple(f"{t}.position" for t in config.names), k), (OMEGA, n), (OMEGA_DOT, n), (S, n)]
                          + effect_inputs("accelerometer", config.names, k)
                          + ([(g, i) for i in (prev[n], nxt[n]) for g in (OMEGA_DOT, S)]
                             if fxs.need(effects, fxs.RATE) else []),
                          np.zeros((len(k), 0)), valid=ok, series=n, shared_data=R_COLUMNS)]
    if gyro_triads:
        k, n, ok = instances("gyro", gyro_triads)
        need_wd, need_f, need_rate = _gyro_needs(fxs.acting_on(config.effects, "gyroscope"), config.age_order)
        blocks.append(FactorBlock("gyroscope_sample", gyroscope_sample_factor(config),
                                  [(tuple(group_name(t, "gyroscope", g) for t in gyro_triads), k) for g in GYRO_FACTOR_GROUPS]
                                  + [(OMEGA, n)] + ([(OMEGA_DOT, n)] if need_wd else [])
                                  + ([(tuple(f"{t}.position" for t in gyro_triads), k), (S, n)] if need_f else [])
                                  + effect_inputs("gyroscope", gyro_triads, k)
                                  + ([(OMEGA_DOT, prev[n]), (OMEGA_DOT, nxt[n])] if need_rate else []),
                                  np.zeros((len(k), 0)), valid=ok, series=n, shared_data=R_COLUMNS))
    if config.process_model and N > 1:
        a, b = np.arange(N - 1), np.arange(1, N)
        blocks.append(FactorBlock("process_model", process_factor(config.motion.integration),
                                  [(OMEGA, a), (OMEGA_DOT, a), (S, a), (OMEGA, b), (OMEGA_DOT, b), (S, b)]
                                  + ([(OMEGA_DDOT, a), (OMEGA_DDOT, b)] if snap else []),
                                  np.zeros((N - 1, 0)), series=a))
    problem = DynamicProblem(config, LeastSquaresProblem(Layout(groups), blocks), N, gyro_triads, rows, axes)
    for blk, d in zip(blocks, problem.block_data(data)):
        blk.data = d
    return problem


#: σ of a masked (saturated) reading in :func:`build_dynamic_sigma_masked`: its whitened residual
#: and Jacobian vanish (to 1e-30 of the others), as if the reading were left out.
MASKED_SIGMA = 1e30


def build_dynamic_sigma_masked(config: DynamicConfig, data: DynamicData) -> DynamicProblem:
    """The dynamic problem with every sample an instance, masked readings weighted out by σ = MASKED_SIGMA.

    Same optimum as :func:`build_dynamic` (which leaves masked readings out), but the structure no
    longer depends on which samples saturate: a fixed-size solver (the C code) takes any window.
    The start is that of the masked problem (gyro-aided, interpolated over saturated gyros)."""
    full = replace(data, acc_valid={}, gyro_valid={})
    problem = build_dynamic(config, full, initial_motion(config, data, _gyro_triads(config, data)))
    blocks = problem.block_data(full)
    for kind, names, blk in (("acc", config.names, blocks[0]),
                             ("gyro", problem.gyro_triads, blocks[1] if problem.gyro_triads else None)):
        for k, name in enumerate(names):
            blk[k::len(names), 3:6][~data.axis_valid(kind, name)] = MASKED_SIGMA  # sample-major
    for b, d in zip(problem.lsq.blocks, blocks):
        b.data = d
    return problem


@dataclass
class JointProblem(DynamicProblem):
    """Static poses and the dynamic phase of one recording in a single problem: the triads'
    intrinsics are shared, the static blocks (Nilsson 2014) determine them from gravity, the dynamic
    blocks add the geometry. Dynamic blocks come first, so residuals split as in a dynamic problem."""

    static: object = None  # the StaticProblem whose blocks and pose directions are included


def build_joint(static_problem, config: DynamicConfig, data: DynamicData) -> JointProblem:
    """Merge a static problem (built on the static poses) and a dynamic problem of the same triads."""
    dyn = build_dynamic(config, data)
    names = {g.name for g in dyn.lsq.layout.groups}
    groups = dyn.lsq.layout.groups + [g for g in static_problem.lsq.layout.groups if g.name not in names]
    lsq = LeastSquaresProblem(Layout(groups), dyn.lsq.blocks + static_problem.lsq.blocks)
    return JointProblem(config, lsq, dyn.n_samples, dyn.gyro_triads, dyn.rows, dyn.axes, static_problem)
