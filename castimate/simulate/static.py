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


def _slerp_directions(u0: np.ndarray, u1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Great-circle interpolation between unit vectors for s in [0, 1]."""
    ang = np.arccos(np.clip(u0 @ u1, -1, 1))
    if ang < 1e-9:
        return np.repeat(u0[None], len(s), axis=0)
    return (np.sin((1 - s) * ang)[:, None] * u0 + np.sin(s * ang)[:, None] * u1) / np.sin(ang)


def static_time_series(truth: StaticTruth, U: np.ndarray, sigma: float, rng: np.random.Generator, *,
                       rate: float = 100.0, pose_duration: float = 10.0, transition: float = 3.0,
                       gyro_sigma: float | None = None) -> tuple[Recording, list[tuple[float, float]]]:
    """A raw static session: each pose held for ``pose_duration`` s, joined by smooth rotations.

    During a transition the specific force follows a great circle with a smooth (raised-cosine)
    speed profile and the gyroscopes see the corresponding rotation rate; the small centripetal
    terms are ignored. Returns the recording and the true static intervals in seconds.
    """
    n_hold, n_move = int(round(pose_duration * rate)), int(round(transition * rate))
    dirs, omega, intervals = [], [], []
    t_now = 0.0
    for i, u in enumerate(U):
        dirs.append(np.repeat(u[None], n_hold, axis=0))
        omega.append(np.zeros((n_hold, 3)))
        intervals.append((t_now, t_now + n_hold / rate))
        t_now += n_hold / rate
        if i + 1 < len(U):
            s = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n_move + 1) / (n_move + 1))
            path = _slerp_directions(u, U[i + 1], s)
            dirs.append(path)
            axis = np.cross(u, U[i + 1])
            axis = axis / (np.linalg.norm(axis) or 1.0)
            ang = np.arccos(np.clip(u @ U[i + 1], -1, 1))
            ds = np.gradient(s) * rate
            omega.append(-ang * ds[:, None] * axis[None])  # the body turns opposite to the apparent force
            t_now += n_move / rate
    D, W = np.vstack(dirs), np.vstack(omega)
    t = np.arange(len(D)) / rate
    acc = {n: truth.gravity * D @ truth.T(n).T + truth.b(n) + sigma * rng.standard_normal(D.shape)
           for n in truth.names}
    gyro = {}
    if gyro_sigma is not None:
        gyro = {n: W @ truth.R_nominal[n].T + truth.values[f"{n}.gyroscope.bias"]
                + gyro_sigma * rng.standard_normal(D.shape) for n in truth.names}
    return Recording(t=t, acc=acc, gyro=gyro, source="simulation"), intervals
