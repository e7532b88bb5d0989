"""The in-memory form of a recording, shared by every reader."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from castimate.io.timestamps import TimeBase


@dataclass(frozen=True)
class Recording:
    """A time series of an inertial sensor array in SI units.

    Attributes
    ----------
    t
        Sample times, shape (N,), seconds, strictly increasing.
    acc
        Triad name -> specific force readings, shape (N, 3), m/s^2 (after the declared
        unit conversion; still *uncalibrated*).
    gyro
        Triad name -> angular rate readings, shape (N, 3), rad/s (uncalibrated). Triads
        without a gyroscope are absent.
    temp
        Triad name -> temperature, shape (N,), K, where logged.
    source
        The file(s) it was read from, for error messages.
    notes
        Human-readable remarks from the reader (dropped packets, resynchronisations, the time base).
    rails
        Sensor (``accelerometer``, ``gyroscope``) -> triad name -> (2, 3) the low and high rail per axis
        (SI units): the converter's extreme counts after the reader's unit conversion, where the reader
        knows them (MIMU int16 packets; counts declared with ``rails``). Absent: not known.
    time_base
        How the reader obtained ``t`` from the file's stamps: rate, repairs, gaps
        (:class:`castimate.io.timestamps.TimeBase`); None where no reader made it.
    """

    t: np.ndarray
    acc: dict[str, np.ndarray]
    gyro: dict[str, np.ndarray] = field(default_factory=dict)
    temp: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""
    notes: tuple[str, ...] = ()
    rails: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    time_base: TimeBase | None = None

    @property
    def triads(self) -> list[str]:
        return list(self.acc)

    def rails_of(self, name: str, sensor: str) -> np.ndarray | None:
        """(2, 3) [low; high] rails of a triad's sensor in SI units, or None where not known."""
        return self.rails.get(sensor, {}).get(name)

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: np.ndarray) -> "Recording":
        """The samples where ``mask`` is true."""
        return Recording(
            t=self.t[mask],
            acc={k: v[mask] for k, v in self.acc.items()},
            gyro={k: v[mask] for k, v in self.gyro.items()},
            temp={k: v[mask] for k, v in self.temp.items()},
            source=self.source,
            notes=self.notes,
            rails=self.rails,
            time_base=self.time_base,
        )
