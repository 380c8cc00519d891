"""The workbench loop's settings: :class:`WorkbenchSettings` gathers the settings of each stage (calibration,
score tests, refits, closure, diagnostics), each a frozen dataclass whose field defaults are the only
place a default lives; ``conf/workbench.yaml`` sets what differs and ``phm-workbench`` instantiates one
config node per dataclass (:func:`phm_torch.apps.workbench.settings_from_config`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .. import checks
from ..effects import EFFECTS
from .calibrate import FitSettings
from .candidates import ScoreSettings
from .closure import ClosureSettings
from .diagnostics import DiagnosticSettings


def _free_parameters(value: Mapping[str, Sequence[str]] | None, name: str) -> dict[str, tuple[str, ...]]:
    """``{effect: [parameter, ...]}`` as a dict of tuples (the names are checked by :class:`WorkbenchSettings`)."""
    return {effect: checks.names(keys, f"{name}.{effect}") for effect, keys in checks.mapping(value, name).items()}


@dataclass(frozen=True)
class RefitSettings:
    """Confirmation of the top candidates (the ``refit`` node of ``conf/workbench.yaml``).

    Attributes:
        top: testable candidates refitted (together, one simulator call per iteration) in each round.
        rounds: add the best confirmed candidate and rank again, up to this many times.
        free: {effect: [parameter, ...]} fitted when the effect is added, besides its strength (an effect
            not listed: its strength parameters only); the names are checked by :class:`WorkbenchSettings`.
        fit: Levenberg-Marquardt settings of the refits.
    """

    top: int = 3
    rounds: int = 2
    free: Mapping[str, Sequence[str]] = field(default_factory=dict)
    fit: FitSettings = field(default_factory=lambda: FitSettings(max_iter=6))

    def __post_init__(self) -> None:
        object.__setattr__(self, "top", checks.integer(self.top, "refit.top", 0))
        object.__setattr__(self, "rounds", checks.integer(self.rounds, "refit.rounds", 0))
        object.__setattr__(self, "free", _free_parameters(self.free, "refit.free"))
        if not isinstance(self.fit, FitSettings):
            raise ValueError(f"refit.fit must be FitSettings, got {self.fit!r}")


_REFIT = RefitSettings()  # the defaults of the refit fields below


@dataclass(frozen=True)
class WorkbenchSettings:
    """Every tunable of the loop.

    Attributes:
        calibration: Levenberg-Marquardt settings of the calibration (one batched simulator call per
            iteration; see :class:`FitSettings`).
        refit, refit_top, rounds, refit_free: the refits of the top candidates (:class:`RefitSettings`'s
            ``fit``, ``top``, ``rounds`` and ``free``; :meth:`of` builds the settings from one).
        score: the score tests.  diagnostics: where the model fails.  closure: the neural closure.
        library: candidate effects; ``None``: every registered effect not in the model.
        before_after: with effects in the model, also fit the datasheet model without them ("before").
        fd_step: forward-difference step of the normalised parameters (log-multiplier, k, or effect value /
            its scale); large enough to step over stick-slip events.
    """

    calibration: FitSettings = field(default_factory=FitSettings)
    refit: FitSettings = _REFIT.fit
    score: ScoreSettings = field(default_factory=ScoreSettings)
    diagnostics: DiagnosticSettings = field(default_factory=DiagnosticSettings)
    closure: ClosureSettings = field(default_factory=ClosureSettings)
    refit_top: int = _REFIT.top
    rounds: int = _REFIT.rounds
    refit_free: Mapping[str, Sequence[str]] = field(default_factory=lambda: dict(_REFIT.free))
    library: Sequence[str] | None = None
    before_after: bool = True
    fd_step: float = 1e-2

    @classmethod
    def of(cls, refit: RefitSettings, **settings: Any) -> WorkbenchSettings:
        """The settings with ``refit``'s fit, candidates, rounds and free parameters, ``settings`` the rest."""
        return cls(refit=refit.fit, refit_top=refit.top, rounds=refit.rounds, refit_free=refit.free, **settings)

    def __post_init__(self) -> None:
        for name, kind in (
            ("calibration", FitSettings),
            ("refit", FitSettings),
            ("score", ScoreSettings),
            ("diagnostics", DiagnosticSettings),
            ("closure", ClosureSettings),
        ):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be {kind.__name__}, got {getattr(self, name)!r}")
        if self.refit_top < 0 or self.rounds < 0:
            raise ValueError(f"refit_top and rounds must be >= 0, got {self.refit_top}, {self.rounds}")
        refit_free = _free_parameters(self.refit_free, "refit_free")
        for effect, keys in refit_free.items():
            if effect not in EFFECTS:
                raise ValueError(f"refit_free: unknown effect {effect!r}; available: {sorted(EFFECTS)}")
            bad = [k for k in keys if k not in EFFECTS[effect].PARAMS]
            if bad:
                raise ValueError(
                    f"refit_free.{effect}: unknown parameter(s) {bad}; known: {sorted(EFFECTS[effect].PARAMS)}"
                )
        object.__setattr__(self, "refit_free", refit_free)
        if self.library is not None:
            library = checks.names(self.library, "library")
            bad = [n for n in library if n not in EFFECTS]
            if bad:
                raise ValueError(f"library: unknown effect(s) {bad}; available: {sorted(EFFECTS)}")
            object.__setattr__(self, "library", library)
        object.__setattr__(self, "before_after", checks.flag(self.before_after, "before_after"))
        object.__setattr__(self, "fd_step", checks.number(self.fd_step, "fd_step", 0.0, True))
