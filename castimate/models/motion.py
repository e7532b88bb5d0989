"""Rigid-body motion: the specific force at a point and the motion process model.

Motion states per sample (body frame): angular rate ω [rad/s], angular acceleration ω̇ [rad/s²] and
the specific force s [m/s²] at the body origin (gravity included).
"""

from __future__ import annotations

import casadi as ca


def specific_force_at(s, omega, omega_dot, r):
    """f = s + ω×(ω×r) + ω̇×r: specific force at position r [m] of a rigid body
    (Carlsson 2017, eq. 1: centrifugal and Euler terms)."""
    return s + ca.cross(omega, ca.cross(omega, r)) + ca.cross(omega_dot, r)


def specific_force_rate(s_dot, omega, omega_dot, omega_ddot, r):
    """ḟ = ṡ + ω̈×r + ω̇×(ω×r) + ω×(ω̇×r): the time derivative of :func:`specific_force_at`
    (what a triad's sample age acts on, see ``models.effects.sample_age``)."""
    return s_dot + ca.cross(omega_ddot, r) + ca.cross(omega_dot, ca.cross(omega, r)) + ca.cross(omega, ca.cross(omega_dot, r))


def process_residual(omega, omega_dot, s, omega_next, omega_dot_next, s_next, dt, sigma_s, sigma_int, sigma_omega_dot):
    """Whitened process-model residual between samples n and n+1 (Schopp 2016, eqs. 7, 8, 14).

    ω_{n+1} = ω_n + ω̇_n Δt, with ω̇ and s random walks. The covariance is Δt² diag(σ_s², σ_int², σ_ω̇²),
    so each residual is divided by its σ times Δt.
    """
    return ca.vertcat(
        (s_next - s) / (sigma_s * dt),
        (omega_next - omega - omega_dot * dt) / (sigma_int * dt),
        (omega_dot_next - omega_dot) / (sigma_omega_dot * dt),
    )
