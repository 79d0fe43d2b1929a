"""Every event of the signal chain, in one place (as h11 keeps its events in one module).

Two levels, both in absolute sample indices (the sensor's index on the host's timeline, samples at ``fs``):

- the **detector's** decisions (:class:`Onset`, :class:`Offset`; :class:`Quiet`, :class:`Loud`, :class:`Pause` and
  :class:`Resume` within a slide), from tactiled/core/detect.py: where a slide began and ended, and the index up to
  which the detector had seen samples when it decided (``at``);
- the **pipeline's** events (:class:`SlideStarted`, :class:`SlideEnded`, :class:`SlideResult`), from
  tactiled/core/pipeline.py: numbered slides and their labels, what the daemon publishes (the wire messages
  of ``tactiled_client.schema``: ``Slide`` and ``Roughness``) and what replay returns.

Nothing here computes: plain frozen or mutable records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class Onset:
    """The detector saw a slide begin at absolute index ``start`` (which may lie before the samples just fed: the
    onset is moved back over the rise that preceded the decision); ``at``: the index up to which it had seen samples
    when it decided (-1: unknown), the windows of the slide the pipeline reads before its end. A slide reported with its
    end already past (the slides a stream began in, known only once the quiet after them showed the floor) has that end
    as the ``at`` of its Onset and Offset: no window after it is its own. The pipeline turns it into :class:`SlideStarted`."""

    start: int
    at: int = -1


@dataclass(frozen=True)
class Offset:
    """The detector saw a slide end: it covered absolute indices [``start``, ``stop``) (``stop`` one past its last
    sample), ended for ``reason`` (``quiet``, ``max_duration``, ``end_of_stream``, or ``too_short``: not a slide);
    ``at`` as in :class:`Onset`. The pipeline turns it into :class:`SlideEnded`."""

    start: int
    stop: int
    reason: str = "quiet"
    at: int = -1


@dataclass(frozen=True)
class Pause:
    """A slide in progress has been quiet since ``stop`` for ``detector.end_hold_s``: probably its end, not yet certain
    (that takes ``off_hold_s``). Either an :class:`Offset` at the same ``stop`` or a :class:`Resume` follows; ``at`` as in
    :class:`Onset`. The pipeline publishes the slide's end and final label at once (low latency)."""

    start: int
    stop: int
    at: int = -1


@dataclass(frozen=True)
class Resume:
    """The quiet after a :class:`Pause` at ``stop`` was a dip: the slide that began at ``start`` goes on; ``at`` as in :class:`Onset`."""

    start: int
    stop: int
    at: int = -1


@dataclass(frozen=True)
class Quiet:
    """A slide in progress went quiet at ``stop`` (its end, or a dip: a :class:`Pause`, an :class:`Offset` or a
    :class:`Loud` follows); ``at`` as in :class:`Onset`. The pipeline holds back the provisional labels of windows that
    reach past ``stop`` until it knows which."""

    start: int
    stop: int
    at: int = -1


@dataclass(frozen=True)
class Loud:
    """The quiet of a slide in progress (its :class:`Quiet`) ended before a :class:`Pause`: a dip, and the slide goes on;
    ``at`` as in :class:`Onset`."""

    start: int
    at: int = -1


DetectorEvent = Onset | Offset | Pause | Resume | Quiet | Loud


@dataclass
class SlideStarted:
    """Slide ``slide_id`` (counted from 0 since the pipeline started) began at absolute index ``start``."""

    slide_id: int
    start: int


@dataclass
class SlideEnded:
    """Slide ``slide_id`` covered absolute indices [``start``, ``stop``) and ended for ``reason`` (quiet | max_duration |
    end_of_stream | too_short); a :class:`SlideResult` follows unless it was too short (then it was no slide)."""

    slide_id: int
    start: int
    stop: int
    reason: str


@dataclass
class SlideResult:
    """The label of one slide (``final``), or a provisional label while it goes on (``final`` False).

    Indices are absolute samples: the slide [``start``, ``stop``), the analysis ``window`` span of the windows used.
    ``label`` is None when the pipeline abstains, with ``reason`` (e.g. ``unknown_surface``, ``low_confidence``,
    ``no_model``, or why no window could be analysed); ``confidence`` is the calibrated probability (0–1) that the
    top class is right and ``top`` the classifier's (label, score) pairs, best first (at most 3). ``quality`` sums
    the windows' samples, lost samples and spikes, and gives the largest clipped (saturated) fraction and the number
    of windows used. ``features`` (F,) are the last window's feature values, ``compute_ms`` the analysis time of this
    result, ``used_s`` the seconds of the slide (from its start) the label is based on, ``novelty`` the distance to
    the training data over the model's threshold (> 1: unlike every surface it was trained on; None: the model has
    no novelty data), ``model`` the fingerprint of the model that made it (models can be swapped between slides).
    """

    slide_id: int
    start: int
    stop: int
    window: tuple[int, int]
    label: str | None
    reason: str | None
    confidence: float | None
    top: list[tuple[str, float]]
    quality: dict[str, Any]
    features: npt.NDArray[np.float64] | None = field(default=None, repr=False)
    compute_ms: float = 0.0
    final: bool = True
    used_s: float = 0.0
    novelty: float | None = None
    model: str = ""


@dataclass
class SlideResumed:
    """Slide ``slide_id``, said to have ended at ``stop`` (a :class:`SlideEnded` and a final :class:`SlideResult` were
    emitted after a short quiet), goes on: that end and that label are withdrawn; a new end and final label follow."""

    slide_id: int
    start: int
    stop: int


PipelineEvent = SlideStarted | SlideEnded | SlideResult | SlideResumed
