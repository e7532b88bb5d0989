"""Ground-truth sessions for the static array model.

The truth is evaluated with an independent numpy implementation of the model (not the CasADi
expressions the solver uses), so recovery tests also cross-check the symbolic model.
Parameter values are keyed by the same group names the solver reports
(``imu2.accelerometer.gain``), so truth and estimate compare directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.recording import Recording
from .effects import sample_terms


def icosahedron_face_normals() -> np.ndarray:
    """The 20 outward unit face normals of a regular icosahedron, (20, 3) (Nilsson 2014, sec. III)."""
    phi = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0], [0, -1, phi], [0, 1, phi],
                  [0, -1, -phi], [0, 1, -phi], [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1]], float)
    F = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    U = np.array([V[list(f)].mean(axis=0) for f in F])
    return U / np.linalg.norm(U, axis=1, keepdims=True)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation matrix."""
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def pose_directions(n_poses: int, rng: np.random.Generator) -> np.ndarray:
    """Specific-force directions (body frame) of n static poses: icosahedron faces, each block of
    20 in a random overall orientation (the array sits in the solid at an unknown angle)."""
    blocks = [icosahedron_face_normals() @ random_rotation(rng).T for _ in range(-(-n_poses // 20))]
    return np.vstack(blocks)[:n_poses]


def _skew(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def triad_matrix(k, l, xi, R_nominal=np.eye(3)) -> np.ndarray:
    """T = diag(k) unitri(l) (I + [xi]x) Rbar (Nilsson 2014, eq. 3), in numpy."""
    L = np.array([[1, 0, 0], [l[0], 1, 0], [l[1], l[2], 1]], float)
    return np.diag(k) @ L @ (np.eye(3) + _skew(xi)) @ R_nominal


@dataclass(frozen=True)
class StaticTruthScale:
    """Standard deviations of the random true parameters (physical units)."""

    gain: float = 0.01  # -
    bias: float = 0.3  # m/s^2
    nonorthogonality: float = 0.005  # rad
    misalignment: float = 0.01  # rad
    gyro_bias: float = 0.02  # rad/s
    gyro_gain: float = 0.0  # -, drawn only when positive
    gyro_misalignment: float = 0.0  # rad, drawn only when positive


@dataclass
class StaticTruth:
    """True parameters of a simulated array."""

    names: list[str]
    reference: str
    gravity: float
    R_nominal: dict[str, np.ndarray]
    values: dict[str, np.ndarray] = field(default_factory=dict)  # group name -> value

    def T(self, name: str) -> np.ndarray:
        v = self.values
        xi = v.get(f"{name}.accelerometer.misalignment", np.zeros(3))
        return triad_matrix(v[f"{name}.accelerometer.gain"], v[f"{name}.accelerometer.nonorthogonality"], xi,
                            self.R_nominal[name])

    def b(self, name: str) -> np.ndarray:
        return self.values[f"{name}.accelerometer.bias"]

    def Tg(self, name: str) -> np.ndarray:
        """T_g = diag(k_g) (I + [xi_g]x) Rbar of the gyroscope (unit gain, no misalignment unless set)."""
        v = self.values
        k, xi = v.get(f"{name}.gyroscope.gain", np.ones(3)), v.get(f"{name}.gyroscope.misalignment", np.zeros(3))
        return np.diag(k) @ (np.eye(3) + _skew(xi)) @ self.R_nominal[name]

    def to_dict(self) -> dict:
        triads = {}
        for n in self.names:
            params = {k.split(".", 1)[1]: v.tolist() for k, v in self.values.items() if k.startswith(n + ".")}
            triads[n] = {"accelerometer": {"T": self.T(n).tolist(), "b": self.b(n).tolist()},
                         "R_nominal": self.R_nominal[n].tolist(), "parameters": params}
        return {"format": "castimate.truth/1", "gravity": self.gravity, "reference": self.reference,
                "triads": triads}


def random_static_truth(names: list[str], reference: str, rng: np.random.Generator, gravity: float = 9.81,
                        scale: StaticTruthScale = StaticTruthScale(), gyroscope: bool = False,
                        R_nominal: dict[str, np.ndarray] | None = None) -> StaticTruth:
    """Random true parameters around the nominal ones; the reference triad has no misalignment."""
    R_nominal = R_nominal or {n: np.eye(3) for n in names}
    truth = StaticTruth(list(names), reference, gravity, R_nominal)
    for n in names:
        v = truth.values
        v[f"{n}.accelerometer.gain"] = 1 + scale.gain * rng.standard_normal(3)
        v[f"{n}.accelerometer.bias"] = scale.bias * rng.standard_normal(3)
        v[f"{n}.accelerometer.nonorthogonality"] = scale.nonorthogonality * rng.standard_normal(3)
        if n != reference:
            v[f"{n}.accelerometer.misalignment"] = scale.misalignment * rng.standard_normal(3)
        if gyroscope:
            v[f"{n}.gyroscope.bias"] = scale.gyro_bias * rng.standard_normal(3)
            if scale.gyro_gain > 0:
                v[f"{n}.gyroscope.gain"] = 1 + scale.gyro_gain * rng.standard_normal(3)
            if scale.gyro_misalignment > 0:
                v[f"{n}.gyroscope.misalignment"] = scale.gyro_misalignment * rng.standard_normal(3)
    return truth


def static_pose_means(truth: StaticTruth, U: np.ndarray, sigma: float, n_samples: int,
                      rng: np.random.Generator, gyro_sigma: float | None = None,
                      tau: np.ndarray | None = None, temperature: dict[str, np.ndarray] | None = None
                      ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Noisy per-pose means (P, 3) of every triad: the mean of n_samples with white noise σ.

    ``tau`` (P,) is each pose's normalised time and ``temperature`` triad -> (P,) its temperature
    [K], for the truth's effects (the temperature regressor is the deviation from its mean).
    """
    P = len(U)
    tau = np.zeros(P) if tau is None else np.asarray(tau, float)
    dT = {n: np.zeros(P) if temperature is None or n not in temperature else temperature[n] - temperature[n].mean()
          for n in truth.names}
    s = sigma / np.sqrt(n_samples)
    acc = {}
    for n in truth.names:
        u = truth.gravity * U @ truth.T(n).T
        acc[n] = u + truth.b(n) + sample_terms(truth.values, n, "accelerometer", u, u, tau, dT[n]) \
            + s * rng.standard_normal(U.shape)
    gyro = {}
    if gyro_sigma is not None:
        sg = gyro_sigma / np.sqrt(n_samples)
        for n in truth.names:
            f = truth.gravity * U @ truth.R_nominal[n].T
            gyro[n] = truth.values[f"{n}.gyroscope.bias"] + \
                sample_terms(truth.values, n, "gyroscope", np.zeros_like(f), f, tau, dT[n]) + sg * rng.standard_normal(U.shape)
    return acc, gyro


def _rotate(axis: np.ndarray, angle: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Rodrigues: u (3,) rotated by angle (N,) about the unit axis (3,), (N, 3)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return u * c + np.cross(axis, u)[None] * s + np.outer(1 - c[:, 0], axis * (axis @ u))


def static_time_series(truth: StaticTruth, U: np.ndarray, sigma: float, rng: np.random.Generator, *,
                       rate: float = 100.0, pose_duration: float | np.ndarray = 10.0,
                       transition: float | np.ndarray = 3.0, gyro_sigma: float | None = None,
                       heading_swing: float = 0.0) -> tuple[Recording, list[tuple[float, float]]]:
    """A raw static session: each pose held for ``pose_duration`` s, joined by smooth rotations of
    ``transition`` s (each a number, or one per pose / per transition).

    During a transition of duration D the specific force turns along the great circle from one pose
    direction to the next, by the angle α about the fixed body axis a, with the raised-cosine
    profile s(τ) = (1 - cos(π τ / D)) / 2; on top, the body swings about the vertical by
    ψ(τ) = ``heading_swing`` sin(π s) (which leaves the specific force alone), so the body-frame
    axis of the rotation wanders and the rotations of successive samples do not commute. The body
    rate is ω = -α ṡ a + ψ̇ u(τ) in closed form. Accelerometers sample u at t_k, gyroscopes the rate
    at the middle of their sample interval [t_k, t_k+1] (what a gyroscope that averages over its
    interval reads, to O(Δt³)); the small centripetal terms are ignored.
    Gyroscopes read T_g ω + b_g with the truth's T_g. Returns the recording and the true static
    intervals in seconds.
    """
    P = len(U)
    n_hold = np.round(np.broadcast_to(np.asarray(pose_duration, float), (P,)) * rate).astype(int)
    n_move = np.round(np.broadcast_to(np.asarray(transition, float), (max(P - 1, 0),)) * rate).astype(int)
    dt = 1 / rate
    intervals, plan, t_now = [], [], 0.0
    for i in range(P):
        intervals.append((t_now, t_now + n_hold[i] / rate))
        t_now += (n_hold[i] + (n_move[i] if i + 1 < P else 0)) / rate
        if i + 1 < P:  # the transition starts at the hold's last sample
            axis = np.cross(U[i], U[i + 1])
            axis = axis / (np.linalg.norm(axis) or 1.0)
            plan.append((intervals[-1][1] - dt, (n_move[i] + 1) / rate, axis,
                         np.arccos(np.clip(U[i] @ U[i + 1], -1, 1))))
    N = int(n_hold.sum() + n_move.sum())
    t = np.arange(N) / rate

    def state(tq):
        """Specific-force direction and body rate at times tq."""
        u, w = np.zeros((len(tq), 3)), np.zeros((len(tq), 3))
        k = np.clip(np.searchsorted([iv[0] for iv in intervals], tq, side="right") - 1, 0, len(U) - 1)
        u[:] = U[k]
        for i, (t0, D, axis, ang) in enumerate(plan):
            m = (tq > t0) & (tq < t0 + D)
            x = (tq[m] - t0) / D
            s, sd = 0.5 - 0.5 * np.cos(np.pi * x), 0.5 * np.pi / D * np.sin(np.pi * x)
            u[m] = _rotate(axis, s * ang, U[i])
            psid = heading_swing * np.pi * np.cos(np.pi * s) * sd
            w[m] = -ang * sd[:, None] * axis[None] + psid[:, None] * u[m]
        return u, w

    D_u, _ = state(t)
    _, W = state(t + dt / 2)
    acc = {n: truth.gravity * D_u @ truth.T(n).T + truth.b(n) + sigma * rng.standard_normal(D_u.shape)
           for n in truth.names}
    gyro = {}
    if gyro_sigma is not None:
        gyro = {n: W @ truth.Tg(n).T + truth.values[f"{n}.gyroscope.bias"]
                + gyro_sigma * rng.standard_normal(D_u.shape) for n in truth.names}
    return Recording(t=t, acc=acc, gyro=gyro, source="simulation"), intervals
