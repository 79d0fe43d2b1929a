"""A candidate model in the shadow of the live one: how often they agree, and how sure and how often unsure the candidate is.

The daemon runs the candidate through a second pipeline on the same samples, which goes on from the live one's detector
(tactiled.run.stream.Stream.set_shadow: the same slides, under the same ids); its final results are compared here with
the live model's, slide by slide, paired by overlap.
Nothing here publishes: the candidate's labels go to their own topic, never as the live ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from tactiled.core.events import SlideResult

PENDING_MAX = 64  # results kept while waiting for the other model's result of the same slide


@dataclass
class ShadowStats:
    """Running comparison of a candidate model's final results with the live model's (pure; no I/O)."""

    model: str = ""  # the candidate's fingerprint
    slides: int = 0  # slides both models gave a final result for
    agreed: int = 0  # ... with the same label (both null counts as agreeing)
    finals: int = 0  # candidate final results
    labelled: int = 0  # ... with a label
    unknown: int = 0  # candidate results null with reason unknown_surface
    confidence_sum: float = 0.0  # over the labelled candidate results
    _live: dict[int, SlideResult] = field(default_factory=dict, repr=False)
    _shadow: dict[int, SlideResult] = field(default_factory=dict, repr=False)
    _paired: dict[int, tuple[int, bool]] = field(default_factory=dict, repr=False)  # live/shadow start -> (other start, agreed)
    _last: dict[bool, SlideResult] = field(default_factory=dict, repr=False)  # the last final result of each (True: shadow)

    def add_live(self, result: SlideResult) -> None:
        """A final result of the live model."""
        if result.final:
            self._last[False] = result
            self._pair(result, self._live, self._shadow)

    def add_shadow(self, result: SlideResult) -> None:
        """A final result of the candidate."""
        if not result.final:
            return
        self._last[True] = result
        self.finals += 1
        if result.label is not None:
            self.labelled += 1
            self.confidence_sum += result.confidence or 0.0
        elif result.reason == "unknown_surface":
            self.unknown += 1
        self._pair(result, self._shadow, self._live)

    def _pair(self, result: SlideResult, mine: dict[int, SlideResult], other: dict[int, SlideResult]) -> None:
        """Pair ``result`` with the other model's result of an overlapping slide (the same slide: both pipelines' slides are
        the same), else keep it waiting."""
        key = next((k for k, r in other.items() if min(r.stop, result.stop) > max(r.start, result.start)), None)
        match = other.pop(key) if key is not None else None
        if match is None:
            mine[result.start] = result
            while len(mine) > PENDING_MAX:  # a slide the other model never finished (a restart): forget the oldest
                mine.pop(next(iter(mine)))
            return
        self.slides += 1
        self.agreed += (result.label == match.label)
        self._paired[result.start] = (match.start, result.label == match.label)
        self._paired[match.start] = (result.start, result.label == match.label)
        while len(self._paired) > 2 * PENDING_MAX:
            self._paired.pop(next(iter(self._paired)))

    def withdraw(self, shadow: bool) -> None:
        """The last final result of the candidate (``shadow``) or of the live model was withdrawn (its slide went on): uncount it."""
        result = self._last.pop(shadow, None)
        if result is None:
            return
        if shadow:
            self.finals -= 1
            if result.label is not None:
                self.labelled -= 1
                self.confidence_sum -= result.confidence or 0.0
            elif result.reason == "unknown_surface":
                self.unknown -= 1
        mine = self._shadow if shadow else self._live
        if mine.pop(result.start, None) is None and result.start in self._paired:
            other, agreed = self._paired.pop(result.start)
            self._paired.pop(other, None)
            self.slides -= 1
            self.agreed -= agreed
            # the other model's result waits again for this slide's new final result
            kept = self._last.get(not shadow)
            if kept is not None and kept.start == other:
                (self._live if shadow else self._shadow)[other] = kept

    def summary(self) -> dict[str, Any]:
        """For the status message: the candidate's fingerprint, slides compared, agreement with the live labels,
        its mean calibrated confidence over its labels, and its unknown-surface rate (None until there is data)."""
        return {"model": self.model, "slides": self.slides,
                "agreement": self.agreed / self.slides if self.slides else None,
                "confidence": self.confidence_sum / self.labelled if self.labelled else None,
                "unknown_rate": self.unknown / self.finals if self.finals else None}
