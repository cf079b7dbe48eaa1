"""The simulated flight: a lawn-mower of straight passes joined by half-circle turns, with multirotor
wobble, as continuous analytic functions of time.

Coordinates are UTM metres (E, N) of the site's zone and altitude above the WGS-84 ellipsoid.
Angles are radians unless a name says ``_deg``. Attitude is body -> NED with N = grid north:
``Rotation.from_euler("ZYX", [yaw_grid, pitch, roll_aero])`` (body x forward, y right wing, z down).

The nominal path lives in a pass frame (a, c): ``a`` along the first pass's grid heading ``psi``,
``c`` to its right. Pass k is the straight line c = (k - (P - 1) / 2) * spacing, flown towards +a
for even k and -a for odd k; a half circle of radius spacing / 2 joins the end of one pass to the
start of the next (``bank_deg`` > 0: a coordinated banked turn instead, see
:mod:`archive.simulator.turns`; ``record_into_turn_s`` > 0: the straight segment ends that long before
the recording of the pass does, so the last lines of each pass but the last are flown in the turn).
Small smooth perturbations (sums of sinusoids of ``tau = t - t_ref``) are added to the along / across
/ altitude position and to roll, pitch and yaw (and the bank of banked turns to the roll).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np
from pyproj import Transformer
from scipy.spatial.transform import Rotation

from archive.simulator.turns import BankedTurn, banked_turn

__all__ = ["FRAMERATE", "INS_RATE", "Trajectory", "Wobble", "convergence", "default_wobble",
           "utm_epsg", "to_lonlat", "to_utm"]

FRAMERATE = 249.0   #: camera lines per second
INS_RATE = 200.0    #: navigation samples per second


@dataclass(frozen=True)
class Wobble:
    """A sum of sinusoids ``offset + sum(amp * sin(2 pi f tau + phase))``; amp in the unit of the
    quantity (m or degrees), f in Hz, phase in rad."""

    offset: float = 0.0
    terms: tuple[tuple[float, float, float], ...] = ()

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        out = np.full(np.shape(tau), float(self.offset))
        for amp, freq, phase in self.terms:
            out += amp * np.sin(2.0 * np.pi * freq * tau + phase)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Wobble:
        return cls(float(d["offset"]), tuple(tuple(float(v) for v in t) for t in d["terms"]))


def default_wobble(rng: np.random.Generator) -> dict[str, Wobble]:
    """Multirotor wobble with random phases: roll/pitch a few degrees at 0.2-0.6 Hz plus 0.25-0.3 deg
    at 2-3 Hz, yaw drift of ~1-2 deg, altitude +-0.5 m at 0.3 Hz, a little lateral drift.

    The high-frequency terms keep amp * (2 pi f)^2 below ~1.3 rad/s^2 each, so that linear / slerp
    interpolation of 200 Hz samples is within ~0.0004 deg and a few micrometres of the truth.
    """
    def ph() -> float:
        return float(rng.uniform(0.0, 2.0 * np.pi))
    return {
        "roll_deg": Wobble(0.0, ((2.0, 0.37, ph()), (1.0, 0.23, ph()), (0.3, 2.3, ph()))),
        "pitch_deg": Wobble(0.0, ((1.3, 0.29, ph()), (0.6, 0.53, ph()), (0.25, 2.7, ph()))),
        "yaw_deg": Wobble(1.0, ((0.8, 0.017, ph()), (0.4, 0.41, ph()), (0.1, 2.1, ph()))),
        "alt_m": Wobble(0.0, ((0.5, 0.3, ph()), (0.15, 0.11, ph()))),
        "across_m": Wobble(0.0, ((0.4, 0.07, ph()), (0.2, 0.13, ph()))),
        "along_m": Wobble(0.0, ((0.3, 0.1, ph()),)),
    }


@dataclass(frozen=True)
class Trajectory:
    """Continuous truth of the platform (= camera) motion.

    epsg: UTM zone of the site; origin_e / origin_n: UTM of the pattern's centre (m).
    heading_deg: grid heading of even passes (odd passes fly heading + 180).
    speed: m/s; spacing: m between pass centre lines; height: m above ground; ground_height: m
    (ellipsoid); t_ref: GPS seconds at which pass 0 starts (its run-in); run_s: straight flight
    before and after recording on each pass (s); record_s: recording time of a full pass (s);
    passes: number of passes; wobble: perturbations (see :func:`default_wobble`).
    bank_deg: 0 for today's flat half-circle turns, else the sustained bank (deg) of coordinated
    turns (:class:`~archive.simulator.turns.BankedTurn`); record_into_turn_s: how long each pass's
    recording goes on into the following turn (s; 0: recording ends ``run_s`` before the turn).
    """

    epsg: int
    origin_e: float
    origin_n: float
    heading_deg: float
    speed: float
    spacing: float
    height: float
    ground_height: float
    t_ref: float
    run_s: float
    record_s: float
    passes: int
    wobble: dict[str, Wobble] = field(default_factory=dict)
    bank_deg: float = 0.0
    record_into_turn_s: float = 0.0

    # --- timeline ---------------------------------------------------------------------------------
    @property
    def segment_s(self) -> float:
        """Duration of one straight pass segment (run-in + recording + run-out), s; with
        ``record_into_turn_s``, run-in + the part of the recording before the turn."""
        if self.record_into_turn_s:
            return self.run_s + self.record_s - self.record_into_turn_s
        return self.record_s + 2.0 * self.run_s

    @property
    def turn_s(self) -> float:
        """Duration of one turn, s."""
        if self.bank_deg:
            return self.turn.duration
        return math.pi * (self.spacing / 2.0) / self.speed

    @property
    def turn(self) -> BankedTurn | None:
        """The banked turn between passes (None for the flat half-circle turns)."""
        return banked_turn(float(self.speed), float(self.spacing), float(self.bank_deg)) if self.bank_deg else None

    @property
    def period_s(self) -> float:
        return self.segment_s + self.turn_s

    def record_start(self, k: int) -> float:
        """GPS time of the first line of pass ``k`` (s)."""
        return self.t_ref + k * self.period_s + self.run_s

    def segment_end(self, k: int) -> float:
        """GPS time at which the straight segment of pass ``k`` ends (its turn starts)."""
        return self.t_ref + k * self.period_s + self.segment_s

    def turning(self, t) -> np.ndarray:
        """True at GPS times ``t`` flown in a turn between passes."""
        tau = np.asarray(t, float) - self.t_ref
        k = np.clip(np.floor(tau / self.period_s), 0, self.passes - 1).astype(int)
        return (tau - k * self.period_s > self.segment_s) & (k < self.passes - 1)

    def nominal_bank(self, t) -> np.ndarray:
        """Roll (aerospace sign, rad) of the banked turns at GPS times ``t``, without the wobble
        (0 on the passes and everywhere when ``bank_deg`` is 0)."""
        tau = np.asarray(t, float) - self.t_ref
        if not self.bank_deg:
            return np.zeros_like(tau)
        k = np.clip(np.floor(tau / self.period_s), 0, self.passes - 1).astype(int)
        s = tau - k * self.period_s
        turning = (s > self.segment_s) & (k < self.passes - 1)
        bank = self.turn.bank(np.where(turning, s - self.segment_s, 0.0))
        # even passes turn right (right wing down, + roll), odd passes turn left
        return np.where(turning, np.where(k % 2 == 1, -bank, bank), 0.0)

    def pass_c(self, k) -> np.ndarray:
        return (np.asarray(k, float) - (self.passes - 1) / 2.0) * self.spacing

    # --- nominal path in the pass frame -------------------------------------------------------------
    def _nominal(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, c, bearing relative to +a) of the unperturbed path at ``tau`` (s since t_ref)."""
        half = self.speed * self.segment_s / 2.0
        radius = self.spacing / 2.0
        k = np.clip(np.floor(tau / self.period_s), 0, self.passes - 1).astype(int)
        s = tau - k * self.period_s
        odd = (k % 2) == 1
        turning = (s > self.segment_s) & (k < self.passes - 1)
        sign = np.where(odd, -1.0, 1.0)
        a = sign * (-half + self.speed * s)
        c = self.pass_c(k)
        rel = np.where(odd, np.pi, 0.0)
        phi = np.where(turning, (s - self.segment_s) * self.speed / radius, 0.0)
        if self.bank_deg:
            x, y, psi, _ = self.turn(np.where(turning, s - self.segment_s, 0.0))
            a = np.where(turning, sign * (half + x), a)
            c = np.where(turning, c + y, c)
            rel = np.where(turning, np.where(odd, np.pi - psi, psi), rel)
            return a, c, rel
        a = np.where(turning, sign * (half + radius * np.sin(phi)), a)
        c = np.where(turning, c + radius * (1.0 - np.cos(phi)), c)
        rel = np.where(turning, np.where(odd, np.pi - phi, phi), rel)
        return a, c, rel

    def pass_frame_to_utm(self, a, c) -> tuple[np.ndarray, np.ndarray]:
        """Pass-frame (a along heading, c to its right), m -> UTM E, N (m)."""
        psi = math.radians(self.heading_deg)
        a = np.asarray(a, float)
        c = np.asarray(c, float)
        e = self.origin_e + a * math.sin(psi) + c * math.cos(psi)
        n = self.origin_n + a * math.cos(psi) - c * math.sin(psi)
        return e, n

    def nominal_a(self, t) -> np.ndarray:
        """Along-track coordinate (m) of the nominal path at GPS times ``t``."""
        return self._nominal(np.asarray(t, float) - self.t_ref)[0]

    # --- truth ----------------------------------------------------------------------------------------
    def euler(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(yaw_grid, pitch, roll_aero) in rad at GPS times ``t`` (any shape)."""
        tau = np.asarray(t, float) - self.t_ref
        _, _, rel = self._nominal(tau)
        w = self.wobble
        yaw = math.radians(self.heading_deg) + rel + np.radians(w["yaw_deg"](tau))
        yaw = np.mod(yaw + np.pi, 2.0 * np.pi) - np.pi
        roll = np.radians(w["roll_deg"](tau))
        if self.bank_deg:
            roll = roll + self.nominal_bank(t)
        return yaw, np.radians(w["pitch_deg"](tau)), roll

    def position(self, t) -> np.ndarray:
        """(..., 3) E, N (UTM m) and altitude (m, ellipsoid) at GPS times ``t``."""
        tau = np.asarray(t, float) - self.t_ref
        a, c, _ = self._nominal(tau)
        w = self.wobble
        e, n = self.pass_frame_to_utm(a + w["along_m"](tau), c + w["across_m"](tau))
        alt = self.ground_height + self.height + w["alt_m"](tau)
        return np.stack([e, n, alt], axis=-1)

    def attitude(self, t) -> Rotation:
        """Body -> NED (grid north) rotations at GPS times ``t`` (1-D)."""
        yaw, pitch, roll = self.euler(np.atleast_1d(t))
        return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=-1))

    def __call__(self, t) -> tuple[np.ndarray, Rotation]:
        t = np.atleast_1d(np.asarray(t, float))
        return self.position(t), self.attitude(t)

    # --- serialisation --------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = asdict(self)
        d["wobble"] = {k: {"offset": v.offset, "terms": [list(t) for t in v.terms]}
                       for k, v in self.wobble.items()}
        for f in fields(self):   # options added later: written only when set (older truths lack them)
            if f.name in _OPTIONAL and d[f.name] == f.default:
                del d[f.name]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Trajectory:
        d = dict(d)
        d["wobble"] = {k: Wobble.from_dict(v) for k, v in d["wobble"].items()}
        return cls(**d)


_OPTIONAL = ("bank_deg", "record_into_turn_s")


# --- projection helpers (pyproj directly, independent of archive.geometry.navigation) ----------------------
def utm_epsg(lon: float, lat: float) -> int:
    """EPSG code of the WGS 84 / UTM zone holding (lon, lat) degrees (no Norway/Svalbard rules)."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


def _transformer(epsg: int, inverse: bool) -> Transformer:
    return (Transformer.from_crs(epsg, 4326, always_xy=True) if inverse
            else Transformer.from_crs(4326, epsg, always_xy=True))


def to_utm(lon, lat, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """Degrees -> UTM E, N (m)."""
    e, n = _transformer(epsg, False).transform(np.asarray(lon, float), np.asarray(lat, float))
    return np.asarray(e, float), np.asarray(n, float)


def to_lonlat(e, n, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """UTM E, N (m) -> longitude, latitude (degrees)."""
    lon, lat = _transformer(epsg, True).transform(np.asarray(e, float), np.asarray(n, float))
    return np.asarray(lon, float), np.asarray(lat, float)


def convergence(lon, lat, epsg: int) -> np.ndarray:
    """Grid bearing of TRUE north at (lon, lat) degrees, rad: ADD it to a true heading to get a grid
    heading. Computed numerically from (lon, lat) and (lon, lat + 1e-5). About +1.69 deg at Memphis
    (west of zone 16's central meridian; the textbook convergence angle gamma is its negative)."""
    e0, n0 = to_utm(lon, lat, epsg)
    e1, n1 = to_utm(lon, np.asarray(lat, float) + 1e-5, epsg)
    return np.arctan2(e1 - e0, n1 - n0)
