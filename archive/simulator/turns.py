"""Banked (coordinated) U-turns between passes: ``archive simulate --bank-deg D``.

A coordinated turn at speed ``v`` and bank ``phi`` turns at the yaw rate ``g tan(phi) / v``. A turn is
a sequence of pieces in a *turn frame* (x along the heading at the start of the turn, y towards the
side of the next pass, heading psi measured from +x towards +y):

- an *arc* of signed heading change ``delta``: the yaw rate rises as a raised cosine over ``RAMP_S``,
  holds the peak ``Omega = g tan(D) / v`` (the sustained bank ``D``), and falls the same way; an arc
  too short to reach the peak is a raised-cosine bump of lower peak;
- a *straight* leg (no yaw rate, no bank).

The U-turn to the next pass (lateral offset ``d`` = pass spacing, heading reversed, back at x = 0):

- when two quarter turns fit (``d`` >= their lateral extent): arc(pi/2), straight leg across, arc(pi/2);
- else a "light-bulb" turn: arc(-beta) away from the next pass, arc(pi/2 + beta), arc(pi/2 + beta),
  arc(-beta), with ``beta`` solved so that the turn ends ``d`` across.

Both are symmetric in time about the turn's middle, so the turn ends at x = 0 (the end of the next
pass is aligned with the end of this one). The bank is ``atan(v * yaw_rate / g)``, right wing down in a
right turn. Heading and yaw rate are closed-form; the position is integrated exactly (Gauss-Legendre per
2 ms node interval) and interpolated by cubic Hermite splines with the exact velocity (error ~1e-10 m).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.interpolate import CubicHermiteSpline

__all__ = ["RAMP_S", "BankedTurn", "G", "banked_turn"]

G = 9.80665          #: m/s^2
RAMP_S = 0.3         #: s, roll-in (and roll-out) time of an arc's yaw rate
NODE_S = 0.002       #: s, spacing of the position nodes
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


class _Piece:
    """One piece of a turn: ``kind`` 'arc' (signed heading change ``delta``) or 'straight'."""

    def __init__(self, kind: str, t0: float, psi0: float, delta: float = 0.0, omega: float = 0.0,
                 length_s: float = 0.0):
        self.kind, self.t0, self.psi0 = kind, t0, psi0
        if kind == "straight":
            self.sign, self.peak, self.plateau, self.duration = 0.0, 0.0, 0.0, length_s
            return
        self.sign = math.copysign(1.0, delta)
        mag = abs(delta)
        if mag >= omega * RAMP_S:
            self.peak, self.plateau = omega, mag / omega - RAMP_S
        else:
            self.peak, self.plateau = mag / RAMP_S, 0.0
        self.duration = 2.0 * RAMP_S + self.plateau

    def rate_psi(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(yaw rate rad/s, heading rad) at times ``s`` since this piece's start (0 <= s <= duration)."""
        if self.kind == "straight":
            return np.zeros_like(s), np.full_like(s, self.psi0)
        w, tau = self.sign * self.peak, RAMP_S
        k = math.pi / tau
        up = s < tau
        down = s > tau + self.plateau
        x = s - (tau + self.plateau)
        rate = np.where(up, 0.5 * w * (1.0 - np.cos(k * s)),
                        np.where(down, 0.5 * w * (1.0 + np.cos(k * x)), w))
        area_up = 0.5 * w * tau
        psi = np.where(up, 0.5 * w * (s - np.sin(k * s) / k),
                       np.where(down, area_up + w * self.plateau + 0.5 * w * (x + np.sin(k * x) / k),
                                area_up + w * (s - tau)))
        return rate, self.psi0 + psi


class BankedTurn:
    """A U-turn of lateral offset ``spacing`` (m) at ``speed`` (m/s) and sustained bank ``bank_deg``.

    ``duration`` (s); :meth:`__call__` gives (x, y, heading, yaw rate) at times since the turn's start;
    ``bank(s)`` the bank angle (rad, >= 0 towards the turn side); ``first_half_s`` the time of the
    turn's middle; ``peak_end_s`` the time the first arc towards the next pass starts rolling out
    (end of its sustained bank); ``peak_bank_deg`` the largest bank reached.
    """

    def __init__(self, speed: float, spacing: float, bank_deg: float):
        self.speed, self.spacing, self.bank_deg = float(speed), float(spacing), float(bank_deg)
        self.omega = G * math.tan(math.radians(bank_deg)) / self.speed
        quarter = self._pieces([math.pi / 2.0, None, math.pi / 2.0], 0.0)
        span = self._integrate(quarter)[1][-1, 1]        # lateral extent of two quarter turns
        if span <= self.spacing:
            self.beta, self.straight_m = 0.0, self.spacing - span
            deltas: list = [math.pi / 2.0, None, math.pi / 2.0]
        else:
            lo, hi = 0.0, math.pi / 2.0
            for _ in range(60):
                beta = 0.5 * (lo + hi)
                lateral = self._integrate(self._pieces(self._bulb(beta), 0.0))[1][-1, 1]
                lo, hi = (beta, hi) if lateral > self.spacing else (lo, beta)
            self.beta, self.straight_m = 0.5 * (lo + hi), 0.0
            deltas = self._bulb(self.beta)
        self.pieces = self._pieces(deltas, self.straight_m / self.speed)
        self.duration = self.pieces[-1].t0 + self.pieces[-1].duration
        self.first_half_s = self.duration / 2.0
        nodes, pos, vel = self._integrate(self.pieces)
        self._spline = CubicHermiteSpline(nodes, pos, vel, axis=0)
        main = next(p for p in self.pieces if p.kind == "arc" and p.sign > 0)
        self.peak_end_s = main.t0 + RAMP_S + main.plateau
        s = np.linspace(0.0, self.duration, 4001)
        self.peak_bank_deg = float(np.degrees(np.max(np.abs(self.bank(s)))))

    @staticmethod
    def _bulb(beta: float) -> list:
        return [-beta, math.pi / 2.0 + beta, math.pi / 2.0 + beta, -beta]

    def _pieces(self, deltas: list, straight_s: float) -> list[_Piece]:
        pieces: list[_Piece] = []
        t, psi = 0.0, 0.0
        for delta in deltas:
            if delta is None:
                piece = _Piece("straight", t, psi, length_s=straight_s)
            elif delta == 0.0:
                continue
            else:
                piece = _Piece("arc", t, psi, delta, self.omega)
            pieces.append(piece)
            t += piece.duration
            psi = float(piece.rate_psi(np.array([piece.duration]))[1][0])
        return pieces

    def _rate_psi(self, pieces: list[_Piece], s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(s, float)
        rate = np.zeros_like(s)
        psi = np.zeros_like(s)
        for k, piece in enumerate(pieces):
            last = k == len(pieces) - 1
            mask = (s >= piece.t0) & ((s <= piece.t0 + piece.duration) if last else (s < piece.t0 + piece.duration))
            if k == 0:
                mask |= s < piece.t0
            if last:
                mask |= s > piece.t0 + piece.duration
            local = np.clip(s[mask] - piece.t0, 0.0, piece.duration)
            rate[mask], psi[mask] = piece.rate_psi(local)
        return rate, psi

    def _integrate(self, pieces: list[_Piece]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        end = pieces[-1].t0 + pieces[-1].duration
        count = max(2, math.ceil(end / NODE_S) + 1)
        nodes = np.linspace(0.0, end, count)
        a, b = nodes[:-1, None], nodes[1:, None]
        s = 0.5 * (a + b) + 0.5 * (b - a) * _GL_X[None, :]
        _, psi = self._rate_psi(pieces, s.ravel())
        psi = psi.reshape(s.shape)
        w = 0.5 * (b - a) * _GL_W[None, :] * self.speed
        steps = np.stack([(w * np.cos(psi)).sum(axis=1), (w * np.sin(psi)).sum(axis=1)], axis=1)
        pos = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        _, psi_n = self._rate_psi(pieces, nodes)
        vel = self.speed * np.stack([np.cos(psi_n), np.sin(psi_n)], axis=1)
        return nodes, pos, vel

    def __call__(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, heading, yaw rate) at times ``s`` (s since the turn's start, clipped to the turn)."""
        s = np.clip(np.asarray(s, float), 0.0, self.duration)
        xy = self._spline(s)
        rate, psi = self._rate_psi(self.pieces, s)
        return xy[..., 0], xy[..., 1], psi, rate

    def bank(self, s) -> np.ndarray:
        """Bank angle (rad) of the coordinated turn at times ``s``: positive towards the turn side."""
        rate, _ = self._rate_psi(self.pieces, np.clip(np.asarray(s, float), 0.0, self.duration))
        return np.arctan(self.speed * rate / G)


@lru_cache(maxsize=32)
def banked_turn(speed: float, spacing: float, bank_deg: float) -> BankedTurn:
    """The (cached) :class:`BankedTurn` of these parameters."""
    return BankedTurn(speed, spacing, bank_deg)
