"""Which model a stream uses: ``run``, ``replay``, ``export`` and ``record --format mcap`` choose it here, once.

An explicit model file must fit the stream (its rate and channels); without one, the shipped model is used where it
fits and a stream it does not fit runs without a model (said once). Each model file is loaded once, checked for speed
once (:func:`tactiled.learn.cost.check_speed`: a model that cannot keep up with the sensor is refused unless forced),
and a config whose analysis sections the model replaces is said once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from tactiled.config import Config
from tactiled.core.analysis import sections_a_model_overrides
from tactiled.errors import ModelError
from tactiled.learn.cost import check_speed
from tactiled.learn.model import Model, default_model_path, load_model

log = logging.getLogger(__name__)


class ModelChoice:
    """Choose the model of each stream: :meth:`for_stream`. ``path``: an explicit model file (None: the shipped one,
    where it fits); ``explicit``: no model unless ``path`` is given (``--no-model``); ``force``: run a model too slow
    for the sensor anyway; ``warn``: where the one-line notes go; ``set_by``: where ``path`` was set (``my.toml: model.path``),
    said before a :class:`ModelError` about it (None: the command line, which names the file itself)."""

    def __init__(self, config: Config, path: str | None = None, *, explicit: bool = False, force: bool = False,
                 check_cost: bool = True, warn: Callable[[str], None] = log.warning, set_by: str | None = None) -> None:
        self.config = config
        self.path = path or None
        self.set_by = set_by
        self.explicit = explicit
        self.force = force
        self.check_cost = check_cost
        self.warn = warn
        self._model: Model | None = None
        self._checked = False

    @property
    def file(self) -> Path | None:
        """The model file in use (what ``systemctl reload`` loads again), or None."""
        if self.path:
            return Path(self.path)
        return None if self.explicit else default_model_path()

    def _load(self) -> Model | None:
        if self._model is None:
            if self.path:
                self._model = load_model(self.path)
            elif not self.explicit and default_model_path().exists():
                self._model = load_model(None)
        return self._model

    def for_stream(self, fs: float, channels: int, where: str) -> Model | None:
        """The model for a stream of ``fs`` Hz and ``channels`` named ``where``: an explicit one that does not fit is a
        :class:`ModelError`; the shipped one that does not fit is said in one line and no model is used."""
        try:
            model = self._load()
        except ModelError as exc:
            raise self._named(exc) from None
        if model is None:
            return None
        try:
            model.check_stream(fs, channels, where, self.path or None)
        except ModelError as exc:
            if self.path:
                raise self._named(exc) from None
            self.warn(f"shipped model not used: {exc}")
            return None
        if not self._checked:
            self._checked = True
            if self.check_cost:
                check_speed(model, self.path or "the shipped model", self.force)
            self._say_settings(model)
        return model

    def _named(self, exc: ModelError) -> ModelError:
        """``exc`` about :attr:`path`, after where it was set (:attr:`set_by`) when that is known."""
        return ModelError(f"{self.set_by}: {exc}") if self.set_by and self.path else exc

    def _say_settings(self, model: Model) -> None:
        """One note when the config sets analysis sections that the model replaces with its own."""
        unused = sections_a_model_overrides(self.config)
        if not unused:
            return
        st = model.settings
        self.warn(f"the model analyses with its own settings (windows of {st.duration_s:g} s from {st.start_s:g} s, spikes {st.spikes}, "
                  f"{len(st.names)} features); not used with a model, only without one (--no-model): the config's "
                  + ", ".join(f"[{s}]" for s in unused))
