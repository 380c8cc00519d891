"""What a sine sweep reads: first harmonics of the position loop over the last measurement window and the window
before it (``frequency_response.py`` measures them). The window before is kept so that a caller can tell a reading
that depends on when it was taken (a response that has not settled, or never becomes periodic) from one that does
not."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Readings:
    """First harmonics of R simulated rows: L and T over the last window and over the window before, (R,)
    complex each, and whether they settled (R,) bool (set by ``_settled``)."""

    last_l: torch.Tensor
    last_t: torch.Tensor
    before_l: torch.Tensor
    before_t: torch.Tensor
    settled: torch.Tensor | None = None

    READ = ("last_l", "last_t", "before_l", "before_t")  # the harmonics, without ``settled``

    def rows(self, index: torch.Tensor | slice) -> Readings:
        """These readings at ``index`` (``settled`` not carried)."""
        return Readings(*(getattr(self, name)[index] for name in self.READ))

    def put(self, index: torch.Tensor, other: Readings) -> None:
        """Overwrite the rows ``index`` of the harmonics with ``other``'s (in place)."""
        for name in self.READ:
            getattr(self, name)[index] = getattr(other, name)

    @property
    def change(self) -> torch.Tensor:
        """(R,) the largest relative change of L and T from the window before to the last."""
        return torch.maximum(
            (self.last_l - self.before_l).abs() / self.last_l.abs().clamp(min=1e-300),
            (self.last_t - self.before_t).abs() / self.last_t.abs().clamp(min=1e-300),
        )

    @property
    def columns(self) -> tuple[torch.Tensor, ...]:
        """(L, T, settled, L before, T before): the order of ``LoopResponse``'s fields after the frequencies."""
        if self.settled is None:
            raise ValueError("readings not checked for settling")
        return self.last_l, self.last_t, self.settled, self.before_l, self.before_t


@dataclass
class LoopResponse:
    """Measured first-harmonic responses.

    Attributes:
        frequencies: (F,) actual test frequencies [Hz], or (B, F) when each vector has its own (refined).
        open_loop: (B, F) complex L(jw) = Theta_lvdt / E.
        closed_loop: (B, F) complex T(jw) = Theta_lvdt / Theta_cmd.
        settled: (B, F) bool, the response settled within ``tolerance`` (``None`` if not checked).
        open_loop_before, closed_loop_before: (B, F) complex, L and T over the window before the last (``None``
            if not read): what one window less would have read.
    """

    frequencies: torch.Tensor
    open_loop: torch.Tensor
    closed_loop: torch.Tensor
    settled: torch.Tensor | None = None
    open_loop_before: torch.Tensor | None = None
    closed_loop_before: torch.Tensor | None = None

    @property
    def before(self) -> LoopResponse:
        """The response as read over the window before the last (``settled`` as this one's)."""
        if self.open_loop_before is None or self.closed_loop_before is None:
            raise ValueError("this response has no readings of the window before the last")
        return LoopResponse(self.frequencies, self.open_loop_before, self.closed_loop_before, self.settled)
