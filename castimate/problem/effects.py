"""The effect library: additional sensor effects as parameter groups a problem can include.

Each :class:`Effect` pairs a pure symbolic term from :mod:`castimate.models.effects` with a
parameter group definition (components, neutral value, scale, unit) and says which sensor and which
problem kinds it applies to and what data it needs. A problem file includes an effect by naming it
like any other group (``model.accelerometer.bias_drift: free``, or per triad); ``castimate
diagnose`` tests the effects a problem does not include.

Regressors an effect term may use (:class:`Context`):

- ``tau``: normalised time τ = (t - t_mid) / t_half ∈ [-1, 1] over the session, as the moments
  (mean τ, mean τ²) over the averaging interval (a static pose) or (τ, τ²) for one sample;
- ``temp``: temperature minus the triad's session mean [K], as (mean, mean of the square);
- ``u``: the triad's noise-free linear reading (T f or T_g ω), sensor frame;
- ``f``: the specific force in the triad's frame (gyroscope g-sensitivity);
- ``T``, ``omega``, ``omega_dot``: the triad matrix and the motion (size effect);
- ``Rbar``: the triad's nominal mounting rotation, body -> triad (offsets given in a chip's frame);
- ``u_dot``: the time derivative of ``u`` (time offsets and sample ages): T_g ω̇ for a gyroscope,
  T ḟ for an accelerometer (``models.motion.specific_force_rate``, with ṡ and ω̈ from the
  neighbouring samples' motion);
- ``u_ddot``: its second derivative (the sample age's second-order term): T_g ω̈ for a gyroscope,
  T f̈ for an accelerometer (``models.motion.specific_force_acceleration``), from the neighbours;
- ``beat``: the chip clock's sawtooth frac(ν t + φ) − ½ (:mod:`castimate.problem.clocks`).

What an entry says about the data it needs (:attr:`Effect.needs`): :data:`TIME` (the sample times),
:data:`TEMPERATURE` (a logged temperature), :data:`SPECIFIC_FORCE` (the specific force at the triad: in a dynamic problem the
motion states s, ω̇ and the triad's position; when a calibration is applied, the compensated
accelerometer of the same IMU), :data:`MOTION` (ω and ω̇ of the sample) and :data:`RATE` (the
reading's time derivative ``u_dot``: in a dynamic problem ω̇ for a gyroscope, the neighbouring samples'
motion for an accelerometer).

How an entry is undone when a calibration is applied is derived from its symbolic term
(:attr:`Effect.undoing`): a term that does not depend on the reading ``u`` is subtracted (closed
form); one that does is removed by Newton steps on the CasADi expression
(:mod:`castimate.problem.compensation`). Entries with ``sample_wise=False`` describe where or when a
triad senses (sensing-element offsets, time offsets, sample ages); they are not undone sample by sample.

Most groups are per triad (``imu3.accelerometer.axis_offsets``). An entry with ``board=True`` is one
group for the whole array, ``array.<sensor>.<name>`` (:func:`group_names`), shared by every triad as
a property of the chip model they all are: ``accelerometer.chip_axis_offsets``, the sensing elements'
offsets in the chip's own frame, is the same physics as ``axis_offsets`` (one term,
:func:`castimate.models.effects.axis_offsets`) with 6 parameters for the board instead of 6 per triad.
It replaces ``axis_offsets`` (:attr:`Effect.instead_of`): a problem includes one of the two, and
diagnose tries the shared one first.

Timing (issue 11, item 4): a triad's sample is a(t) old when the board reads it, so it reads u(t − a)
≈ u − a u̇ + ½ a² ü (:func:`castimate.models.effects.sample_age`): every timing effect adds to the
reading's one age a (:attr:`Effect.age`), and :func:`total` applies the term to their sum (``ü``:
T_g ω̈ and T f̈ from the neighbouring samples; the second order matters at fast hand twisting, where
ω̈ reaches 10⁴–10⁵ rad/s³). The age is
a property of the chip, shared by its accelerometer and gyroscope (:attr:`Effect.shared`): constant
(``accelerometer.age``), drifting with the chip's clock rate (``clock_drift``) or a sawtooth at the
beat between the chip's clock and the board's read-out (``clock_beat``); all relative to the
reference triad's (``clock_beat`` apart, whose ν, φ differ per chip), since an age common to every
chip is the motion's own time axis (a gauge). The gyroscope's filters add their own group delay on top
of its accelerometer's (``gyroscope.delay``: it reads ω(t − a − d)); the accelerometers see ω and ω̇
at their own instant, which makes d identifiable on the reference IMU too. The earlier per-sensor
``time_offset`` (Δt = −a) expressed the same physics twice and is retired (:data:`RETIRED`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable

import casadi as ca

from ..models import effects as fx
from .parameters import XYZ, GroupDef

STATIC, DYNAMIC = "static_array", "dynamic_array"
#: The problem kinds (a problem file's and a results.json's ``kind``).
KINDS = (STATIC, DYNAMIC, "ferraris")
TIME, TEMPERATURE, SPECIFIC_FORCE, MOTION, RATE = "time", "temperature", "specific_force", "motion", "rate"
#: How an effect is undone when a calibration is applied (:attr:`Effect.undoing`).
SUBTRACTED, NEWTON, NOT_SAMPLE_WISE = "subtracted", "newton", "not sample-wise"
POLY = ("x1", "y1", "z1", "x2", "y2", "z2")  # linear then quadratic coefficient per axis


@dataclass(frozen=True)
class Context:
    """Symbolic regressors available to an effect term (see the module docstring); None where the
    problem kind does not provide them."""

    tau: tuple[Any, Any]
    temp: tuple[Any, Any]
    u: Any
    f: Any = None
    T: Any = None
    omega: Any = None
    omega_dot: Any = None
    u_dot: Any = None
    beat: Any = None
    u_ddot: Any = None
    Rbar: Any = None


@dataclass(frozen=True)
class Effect:
    """One additional sensor effect.

    Attributes
    ----------
    name
        The group name in problem files and results (``bias_drift``).
    sensor
        ``accelerometer`` or ``gyroscope``.
    group
        Components, neutral value (no effect), scale and unit of its parameters.
    term
        ``(c, ctx) -> Δy``: what it adds to the reading, in the sensor frame.
    kinds
        Problem kinds it applies to.
    needs
        The data its term uses beyond the reading (module docstring): :data:`TIME`, :data:`TEMPERATURE`,
        :data:`SPECIFIC_FORCE`, :data:`MOTION`, :data:`RATE`.
    title
        One line for reports.
    relative
        Defined relative to the reference triad, whose value stays neutral (a gauge).
    sample_wise
        False for an effect that says where or when the triad senses: not undone sample by sample
        when a calibration is applied.
    shared
        A property of the IMU's chip (its sample clock): the group belongs to the accelerometer
        (every triad has one) and its term also acts on the triad's gyroscope.
    age
        For a timing effect, ``(c, ctx) -> a``: the sample age [s] it adds. :func:`total` sums the ages
        of a reading's timing effects and adds one :func:`castimate.models.effects.sample_age` term of
        the sum (its second order is not a sum of the effects' own); ``term`` is that term for the
        effect alone.
    board
        One group for the whole array (``array.<sensor>.<name>``), shared by every triad: a property
        of the chip model, not of one chip.
    instead_of
        The key of a per-triad effect this one re-parameterises: a problem includes one of the two,
        and diagnose tries this one first.
    gauge
        For a board effect: ``(nominal rotations of the triads) -> (m, n)`` the directions of its
        parameters those mountings leave undetermined (fixed by :func:`castimate.problem.triads.board_groups`).
    """

    name: str
    sensor: str
    group: GroupDef
    term: Callable[[Any, Context], Any]
    kinds: tuple[str, ...] = (STATIC, DYNAMIC)
    needs: tuple[str, ...] = ()
    title: str = ""
    relative: bool = False
    sample_wise: bool = True
    shared: bool = False
    age: Callable[[Any, Context], Any] | None = None
    board: bool = False
    instead_of: str = ""
    gauge: Callable[[Any], Any] | None = None

    @property
    def key(self) -> str:
        return f"{self.sensor}.{self.name}"

    def acts_on(self, sensor: str) -> bool:
        """Whether its term enters ``sensor``'s readings (its own sensor, or both for a shared one)."""
        return self.sensor == sensor or (self.shared and sensor == "gyroscope")

    @property
    def results_key(self) -> str:
        """Its key in a triad's ``parameters`` of results.json (accelerometer effects unprefixed)."""
        return self.name if self.sensor == "accelerometer" else self.key

    @property
    def undoing(self) -> str:
        """How :mod:`castimate.problem.compensation` undoes it, from the symbolic term: :data:`SUBTRACTED`
        if the term does not depend on the reading u, :data:`NEWTON` if it does, :data:`NOT_SAMPLE_WISE`."""
        if not self.sample_wise:
            return NOT_SAMPLE_WISE
        ctx = probe_context()
        term = self.term(ca.SX.sym("c", len(self.group.components)), ctx)
        return NEWTON if ca.depends_on(term, ctx.u) else SUBTRACTED


def probe_context() -> Context:
    """Every regressor as a free symbol (to inspect a term's dependencies)."""
    sym = ca.SX.sym
    return Context(tau=(sym("tau"), sym("tau2")), temp=(sym("dT"), sym("dT2")), u=sym("u", 3), f=sym("f", 3),
                   T=sym("T", 3, 3), omega=sym("omega", 3), omega_dot=sym("omega_dot", 3), u_dot=sym("u_dot", 3),
                   beat=sym("beat"), u_ddot=sym("u_ddot", 3), Rbar=sym("Rbar", 3, 3))


#: The physical range of a timing effect's age [s] (accelerometer.age, gyroscope.delay, the clock_beat
#: amplitude): a sample read more than a second late is not a sample age but a misaligned recording.
TIMING_RANGE = (-1.0, 1.0)


def _timing(name: str, sensor: str, group: GroupDef, age: Callable[[Any, Context], Any], **kw) -> Effect:
    """A timing effect: it adds ``age`` to the reading's sample age (``Effect.age``); its components
    are ages in s, within TIMING_RANGE."""
    return Effect(name, sensor, replace(group, limits=TIMING_RANGE),
                  lambda c, x: fx.sample_age(age(c, x), x.u_dot, x.u_ddot), kinds=(DYNAMIC,),
                  needs=(RATE,), sample_wise=False, age=age, **kw)


def _bias_drift(sensor: str, unit: str, scale: float) -> Effect:
    return Effect("bias_drift", sensor, GroupDef(POLY, (0.0,) * 6, scale, unit),
                  lambda c, x: fx.polynomial(c, *x.tau), needs=(TIME,),
                  title=f"{sensor} bias drift, quadratic in time ({unit} at the session's ends)")


def _temperature_bias(sensor: str, unit: str, scale: float) -> Effect:
    return Effect("temperature_bias", sensor, GroupDef(POLY, (0.0,) * 6, scale, f"{unit}/K, {unit}/K^2"),
                  lambda c, x: fx.polynomial(c, *x.temp), needs=(TEMPERATURE,),
                  title=f"{sensor} bias linear and quadratic in temperature")


EFFECTS: tuple[Effect, ...] = (
    _bias_drift("accelerometer", "m/s^2", 1e-2),
    _temperature_bias("accelerometer", "m/s^2", 1e-3),
    Effect("temperature_gain", "accelerometer", GroupDef(POLY, (0.0,) * 6, 1e-4, "1/K, 1/K^2"),
           lambda c, x: fx.relative_gain_change(c, *x.temp, x.u), needs=(TEMPERATURE,),
           title="accelerometer gain linear and quadratic in temperature"),
    Effect("scale_nonlinearity", "accelerometer", GroupDef(XYZ, (0.0,) * 3, 1e-4, "1/(m/s^2)"),
           lambda c, x: fx.scale_nonlinearity(c, x.u),
           title="accelerometer scale nonlinearity, quadratic per axis"),
    Effect("axis_offsets", "accelerometer", GroupDef(("yx", "yy", "yz", "zx", "zy", "zz"), (0.0,) * 6, 1e-3, "m"),
           lambda c, x: fx.axis_offsets(x.T, c, x.omega, x.omega_dot), kinds=(DYNAMIC,), needs=(MOTION,),
           relative=True, sample_wise=False,
           title="accelerometer sensing-element offsets (size effect): y and z elements relative to x, "
                 "relative to the reference triad's"),
    Effect("chip_axis_offsets", "accelerometer",
           GroupDef(("yx", "yy", "yz", "zx", "zy", "zz"), (0.0,) * 6, 1e-3, "m"),
           lambda c, x: fx.chip_axis_offsets(x.T, x.Rbar, c, x.omega, x.omega_dot), kinds=(DYNAMIC,),
           needs=(MOTION,), sample_wise=False, board=True, instead_of="accelerometer.axis_offsets",
           gauge=fx.chip_offsets_gauge,
           title="accelerometer sensing-element offsets of the chip model (size effect): y and z elements relative "
                 "to x in the chip's frame, shared by every triad of the board"),
    _timing("age", "accelerometer", GroupDef(("a",), (0.0,), 1e-3, "s"), lambda c, x: c,
            relative=True, shared=True,
            title="chip sample age: the IMU's accelerometer and gyroscope read the motion a late "
                 "(constant, relative to the reference triad's)"),
    _bias_drift("gyroscope", "rad/s", 1e-3),
    _temperature_bias("gyroscope", "rad/s", 1e-4),
    Effect("g_sensitivity", "gyroscope",
           GroupDef(("xx", "xy", "xz", "yx", "yy", "yz", "zx", "zy", "zz"), (0.0,) * 9, 1e-4, "rad/s per m/s^2"),
           lambda c, x: fx.g_sensitivity(c, x.f), needs=(SPECIFIC_FORCE,), title="gyroscope g-sensitivity"),
    _timing("delay", "gyroscope", GroupDef(("d",), (0.0,), 1e-3, "s"), lambda c, x: c,
            title="accelerometer-gyroscope delay: the gyroscope reads the motion d later than its own "
                 "accelerometer (filter group delays)"),
    Effect("coupling", "gyroscope", GroupDef(("yx", "zx", "zy"), (0.0,) * 3, 1e-2, "-", limits=(-1.0, 1.0)),
           lambda c, x: fx.coupling(c, x.u), kinds=(DYNAMIC,),
           title="gyroscope cross-axis coupling: unit lower-triangular C in C K_g M_g Rbar (a general 3x3 matrix)"),
    _timing("clock_drift", "accelerometer", GroupDef(("end",), (0.0,), 1e-4, "s"), lambda c, x: c * x.tau[0],
            relative=True, shared=True,
            title="chip clock-rate drift: the IMU's sample age (accelerometer and gyroscope) linear in time, "
                 "its value at the session's end, relative to the reference triad's"),
    _timing("clock_beat", "accelerometer", GroupDef(("A",), (0.0,), 1e-3, "s"),
            lambda c, x: c * x.beat, shared=True,
            title="chip clock: the IMU's sample age (accelerometer and gyroscope) a sawtooth A (frac(ν t + φ) − ½) "
                 "at the beat with the read-out; ν, φ from the implied age"),
)
BY_KEY = {e.key: e for e in EFFECTS}
#: Effects retired from the library ("sensor.name"), with what replaces them: a problem file or a
#: scenario that names one is refused with this message.
RETIRED = {
    "accelerometer.time_offset": "was retired: a chip's constant sample age is accelerometer.age (a = -dt, shared by "
                                 "the IMU's accelerometer and gyroscope, relative to the reference triad's); the "
                                 "gyroscope's extra age over its accelerometer is gyroscope.delay",
    "gyroscope.time_offset": "was retired: the gyroscope's age beyond its own accelerometer's is gyroscope.delay "
                             "(d = -dt of the gyroscope + dt of the accelerometer); the chip's age, shared by both "
                             "sensors, is accelerometer.age",
}


#: The array-wide groups' prefix: ``array.<sensor>.<name>`` (no triad may be called so).
BOARD = "array"


def group_names(e: Effect, triads) -> list[str]:
    """The parameter groups of effect ``e`` in a problem of ``triads``: one per triad, or the board's one."""
    return [f"{BOARD}.{e.key}"] if e.board else [f"{t}.{e.key}" for t in triads]


def effects_for(sensor: str, kind: str) -> dict[str, Effect]:
    """The effects a problem of ``kind`` may include for ``sensor``, by name."""
    return {e.name: e for e in EFFECTS if e.sensor == sensor and kind in e.kinds}


def included(keys, sensor: str) -> list[Effect]:
    """The effects among ``keys`` ("sensor.name") that act on ``sensor``, in library order."""
    return [e for e in EFFECTS if e.key in keys and e.sensor == sensor]


def need(effects, what: str) -> bool:
    """Whether any of ``effects`` needs ``what`` (:data:`TEMPERATURE`, :data:`SPECIFIC_FORCE`, ...)."""
    return any(what in e.needs for e in effects)


def acting_on(keys, sensor: str) -> list[Effect]:
    """The effects among ``keys`` whose terms enter ``sensor``'s readings (shared chip effects act on
    both sensors of a triad), in library order."""
    return [e for e in EFFECTS if e.key in keys and e.acts_on(sensor)]


def total(effects, params, ctx: Context):
    """Σ of the terms of ``effects`` with their parameter vectors ``params`` (0 if none). The timing
    effects' ages are summed into the reading's one sample age a, which adds −a u̇ + ½ a² ü
    (:func:`castimate.models.effects.sample_age`; first order where the context has no ü)."""
    out, age = 0, None
    for e, c in zip(effects, params):
        if e.age is not None:
            age = e.age(c, ctx) if age is None else age + e.age(c, ctx)
        else:
            out = out + e.term(c, ctx)
    return out if age is None else out + fx.sample_age(age, ctx.u_dot, ctx.u_ddot)
