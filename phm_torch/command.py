"""Position commands on the acquisition grid."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass(frozen=True)
class Chirp:
    """Linear chirp theta_cmd(t) = A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))) (the paper's test command).

    Attributes:
        amplitude: A [rad, user side].  f_start, f_end: [Hz].  duration: T [s].
    """

    amplitude: float = 5e-3
    f_start: float = 0.0
    f_end: float = 15.0
    duration: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude) and self.amplitude > 0):
            raise ValueError(f"command.amplitude must be > 0, got {self.amplitude}")
        if not (self.duration > 0 and math.isfinite(self.duration)):
            raise ValueError(f"command.duration must be > 0, got {self.duration}")
        if self.f_start < 0 or self.f_end < 0:
            raise ValueError(f"command frequencies must be >= 0, got {self.f_start}, {self.f_end}")

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """Command [rad] at times t [s] (any shape)."""
        rate = (self.f_end - self.f_start) / self.duration
        return self.amplitude * torch.sin(2.0 * math.pi * (self.f_start * t + 0.5 * rate * t * t))


@dataclass(frozen=True)
class SlewedChirp:
    """A chirp riding on a constant-rate slew: theta_cmd(t) = A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))) + r t.

    The slew turns the motor through whole revolutions at a steady speed while the chirp probes the loop:
    an effect that repeats once per motor revolution (rotor eccentricity: amplitude *and* phase) or per
    commutation sector (a shorted phase) is then seen over its whole period, which a chirp of a few
    radians at the motor cannot show. Its own class, so that the parameters (and hashes) of every plain
    chirp stay what they were.

    Attributes:
        amplitude: A [rad, user side].  f_start, f_end: [Hz].  duration: T [s].
        slew_rate: r [rad/s, user side]; the motor turns N r T over the test (N the gear ratio).
    """

    amplitude: float
    f_start: float
    f_end: float
    duration: float
    slew_rate: float

    def __post_init__(self) -> None:
        Chirp(self.amplitude, self.f_start, self.f_end, self.duration)  # the same checks
        if not math.isfinite(self.slew_rate):
            raise ValueError(f"command.slew_rate must be finite, got {self.slew_rate}")

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """Command [rad] at times t [s] (any shape)."""
        chirp = Chirp(self.amplitude, self.f_start, self.f_end, self.duration)
        return chirp(t) + self.slew_rate * t


@dataclass(frozen=True)
class LogChirp:
    """Exponential (logarithmic) sweep: theta_cmd(t) = A sin(2 pi f0 T (r^(t/T) - 1) / ln r), r = f1 / f0.

    Its instantaneous frequency f0 r^(t/T) spends equal time on each octave: a test that must see a loop's low
    corner and its crossover within one record, as many benches run it. Its own class, so that the parameters
    (and hashes) of every linear chirp stay what they were.

    Attributes:
        amplitude: A [rad, user side].  f_start: f0 > 0 [Hz].  f_end: f1 > 0, != f0 [Hz].  duration: T [s].
    """

    amplitude: float
    f_start: float
    f_end: float
    duration: float

    def __post_init__(self) -> None:
        Chirp(self.amplitude, self.f_start, self.f_end, self.duration)  # the same checks
        if not (self.f_start > 0 and self.f_end > 0 and self.f_start != self.f_end):
            raise ValueError(
                f"command: a log chirp needs f_start > 0, f_end > 0 and f_start != f_end, got {self.f_start}, "
                f"{self.f_end} (a sweep from 0 Hz is the linear chirp, _target_ phm_torch.command.Chirp)"
            )

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """Command [rad] at times t [s] (any shape)."""
        log_ratio = math.log(self.f_end / self.f_start)
        phase = self.f_start * self.duration / log_ratio * torch.expm1(t * (log_ratio / self.duration))
        return self.amplitude * torch.sin(2.0 * math.pi * phase)


@dataclass(frozen=True)
class Sine:
    """theta_cmd(t) = offset + A sin(2 pi f t): a single-frequency test (frequency response)."""

    amplitude: float
    frequency: float
    duration: float
    offset: float = 0.0

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        return self.offset + self.amplitude * torch.sin(2.0 * math.pi * self.frequency * t)


def _floats(values: Any, field: str) -> tuple[float, ...]:
    """``values`` (a YAML list) as a tuple of finite floats, or a ValueError naming ``field``."""
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"command.{field} must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"command.{field} must hold finite numbers, got {list(out)}")
    return out


@dataclass(frozen=True)
class Profile:
    """A piecewise-linear position profile through breakpoints: steps, ramps, trapezoids, doublets, as acceptance
    test procedures write them.

    theta_cmd is linear between consecutive breakpoints, holds the first position before the first time and the last
    after the last; two breakpoints at the same time are a step (the later position from that time on). The
    breakpoints are the command's parameters, so a profile's provenance hash changes with any of them. Every
    simulation starts at rest at 0: a first position other than 0 is a step at t = 0 (a bench that pre-positions
    the actuator records something else; start the profile at 0 and move from there).

    Attributes:
        times: breakpoint times [s], non-decreasing, >= 0, at most two equal in a row.
        positions: theta_cmd at each breakpoint [rad, user side].
        duration: T [s], the record's length (may run past the last breakpoint: the position holds).
    """

    times: tuple[float, ...]
    positions: tuple[float, ...]
    duration: float

    def __post_init__(self) -> None:
        times, positions = _floats(self.times, "times"), _floats(self.positions, "positions")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", positions)
        if len(times) < 2 or len(times) != len(positions):
            raise ValueError(
                f"command: a profile needs >= 2 breakpoints and as many positions as times, got {len(times)} "
                f"times and {len(positions)} positions"
            )
        steps = [b - a for a, b in itertools.pairwise(times)]
        if times[0] < 0 or any(d < 0 for d in steps):
            raise ValueError(f"command.times must be >= 0 and non-decreasing, got {list(times)}")
        if any(a == 0 and b == 0 for a, b in itertools.pairwise(steps)):
            raise ValueError(f"command.times: at most two breakpoints at one time (a step), got {list(times)}")
        if not (math.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"command.duration must be > 0, got {self.duration}")
        if self.amplitude <= 0:
            raise ValueError(f"command.positions: a profile that never leaves 0 tests nothing, got {list(positions)}")

    @property
    def amplitude(self) -> float:
        """The largest |theta_cmd| [rad] (what the sweep's and the step check's sizes derive from)."""
        return max(abs(p) for p in self.positions)

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """Command [rad] at times t [s] (any shape)."""
        times = torch.tensor(self.times, dtype=t.dtype, device=t.device)
        positions = torch.tensor(self.positions, dtype=t.dtype, device=t.device)
        # segment [i - 1, i] with times[i - 1] <= t < times[i]; at a step's time the later segment
        i = torch.searchsorted(times, t.contiguous(), right=True).clamp(1, len(self.times) - 1)
        t0, t1 = times[i - 1], times[i]
        width = t1 - t0
        w = torch.where(width > 0, (t - t0) / torch.where(width > 0, width, 1.0), (t >= t1).to(t.dtype))
        p0, p1 = positions[i - 1], positions[i]
        return p0 + w.clamp(0.0, 1.0) * (p1 - p0)


def profile_from_samples(
    times: Sequence[float] | np.ndarray, positions: Sequence[float] | np.ndarray, tolerance: float
) -> Profile:
    """The :class:`Profile` through as few of a sampled command's points as keep every sample within ``tolerance``
    of it (Ramer-Douglas-Peucker): a bench's recorded command as a test command config, its hash that of every point
    kept.

    Args:
        times: (n,) sample times [s], increasing (the first becomes t = 0).
        positions: (n,) the command at them [rad, user side].
        tolerance: the largest |profile - sample| allowed [rad], > 0.
    """
    t = np.asarray(times, dtype=np.float64)
    x = np.asarray(positions, dtype=np.float64)
    if t.ndim != 1 or t.shape != x.shape or t.size < 2:
        raise ValueError(f"command samples: times and positions must be (n,) with n >= 2, got {t.shape}, {x.shape}")
    if not (np.isfinite(t).all() and np.isfinite(x).all()) or not bool((np.diff(t) > 0).all()):
        raise ValueError("command samples: times must increase and every value be finite")
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be > 0 [rad], got {tolerance!r}")
    t = t - t[0]
    keep = np.zeros(t.size, dtype=bool)
    keep[[0, -1]] = True
    spans = [(0, t.size - 1)]
    while spans:  # split each span at its farthest sample until every sample is within the tolerance
        a, b = spans.pop()
        if b - a < 2:
            continue
        line = x[a] + (x[b] - x[a]) * (t[a + 1 : b] - t[a]) / (t[b] - t[a])
        off = np.abs(x[a + 1 : b] - line)
        i = int(np.argmax(off))
        if off[i] > tolerance:
            keep[a + 1 + i] = True
            spans += [(a, a + 1 + i), (a + 1 + i, b)]
    return Profile(tuple(t[keep].tolist()), tuple(x[keep].tolist()), float(t[-1]))


@dataclass(frozen=True)
class Multisine:
    """A sum of sines theta_cmd(t) = sum_i A_i sin(2 pi f_i t + phi_i): a broadband test of chosen lines.

    Attributes:
        amplitudes: A_i [rad, user side], > 0.  frequencies: f_i [Hz], > 0.  phases: phi_i [rad] (empty: all 0;
            a Schroeder phasing keeps the peak low).  duration: T [s].
    """

    amplitudes: tuple[float, ...]
    frequencies: tuple[float, ...]
    duration: float
    phases: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        amplitudes, frequencies = _floats(self.amplitudes, "amplitudes"), _floats(self.frequencies, "frequencies")
        phases = _floats(self.phases, "phases") or (0.0,) * len(amplitudes)
        for field, value in (("amplitudes", amplitudes), ("frequencies", frequencies), ("phases", phases)):
            object.__setattr__(self, field, value)
        if not amplitudes or len(frequencies) != len(amplitudes) or len(phases) != len(amplitudes):
            raise ValueError(
                f"command: a multisine needs as many frequencies (and phases, if any) as amplitudes, got "
                f"{len(amplitudes)} amplitudes, {len(frequencies)} frequencies, {len(phases)} phases"
            )
        if any(a <= 0 for a in amplitudes) or any(f <= 0 for f in frequencies):
            raise ValueError(
                f"command: a multisine's amplitudes and frequencies must be > 0, got {list(amplitudes)}, "
                f"{list(frequencies)}"
            )
        if not (math.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"command.duration must be > 0, got {self.duration}")

    @property
    def amplitude(self) -> float:
        """sum |A_i| [rad]: the peak the lines can reach together (what the sweep's and the step check's sizes
        derive from)."""
        return float(sum(self.amplitudes))

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """Command [rad] at times t [s] (any shape)."""
        out = torch.zeros_like(t)
        for a, f, phi in zip(self.amplitudes, self.frequencies, self.phases, strict=True):
            out = out + a * torch.sin(2.0 * math.pi * f * t + phi)
        return out


def time_grid(
    duration: float, sample_rate: float, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """Uniform acquisition grid [s]: round(duration * f_s) + 1 samples, both ends included."""
    n = round(duration * sample_rate)
    if n < 2:
        raise ValueError(f"duration {duration} s at {sample_rate} Hz gives fewer than 2 samples")
    return torch.arange(n + 1, dtype=dtype, device=device) / sample_rate


COMMANDS = {
    "chirp": Chirp,
    "slewed_chirp": SlewedChirp,
    "sine": Sine,
    "log_chirp": LogChirp,
    "profile": Profile,
    "multisine": Multisine,
}  # command kinds: conf/command/<name>.yaml composes in the defaults of one


def with_defaults(node: Mapping[str, Any]) -> dict[str, Any]:
    """A command config node as the apps compose it: the parameters a YAML leaves to its class's defaults filled
    in (``conf/command/chirp.yaml`` sets none) and Hydra's ``defaults`` list dropped."""
    out = {k: v for k, v in node.items() if k != "defaults"}
    module, _, name = str(out.get("_target_", "")).rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name) if module else None
    except (ImportError, AttributeError):
        raise ValueError(f"command: unknown _target_ {out.get('_target_')!r}") from None
    if dataclasses.is_dataclass(cls):
        for f in dataclasses.fields(cls):
            if f.init and f.name not in out and f.default is not dataclasses.MISSING:
                out[f.name] = f.default
    return out


def load_command_node(name: str) -> tuple[str, dict[str, Any]]:
    """(name, config node) of ``conf/command/<name>.yaml`` or of a YAML path (the name is then the path).

    Raises:
        ValueError: no such file, or a file that is not a command config (a mapping with a ``_target_``).
    """
    from omegaconf import OmegaConf

    from .params import CONF_DIR, config_file

    path = config_file("command", name)
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    if not isinstance(node, dict) or "_target_" not in node:
        raise ValueError(f"command: {str(path)!r} is not a command config (a mapping with a _target_)")
    return (name if path.parent == CONF_DIR / "command" else str(path)), with_defaults(node)
