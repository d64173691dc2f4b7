"""Topics devices publish on (what they served or received), and who listens.

The console and the MCAP recorder subscribe; devices ask :meth:`Observers.observed`
first so nothing is built for nobody. A topic is ``kind/name`` (``sonar/sonar_ddf``,
``reading/depth``, ``command/vesc_can``); a subscription names a topic, or a kind
with ``/*`` (``sonar/*``), or ``*`` for all. Listeners run synchronously in the
publisher's call and must not block; one that raises is logged and dropped.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Mapping

log = logging.getLogger(__name__)

Listener = Callable[[str, Mapping[str, Any]], None]


class Observers:
    def __init__(self) -> None:
        self._subs: dict[str, list[Listener]] = {}
        self._cache: dict[str, bool] = {}

    def subscribe(self, pattern: str, listener: Listener) -> Callable[[], None]:
        """Listen to ``pattern``; returns the function that unsubscribes."""
        self._subs.setdefault(pattern, []).append(listener)
        self._cache.clear()

        def unsubscribe() -> None:
            subs = self._subs.get(pattern, [])
            if listener in subs:
                subs.remove(listener)
                if not subs:
                    del self._subs[pattern]
            self._cache.clear()
        return unsubscribe

    def _listeners(self, topic: str) -> list[Listener]:
        kind = topic.split("/", 1)[0]
        out: list[Listener] = []
        for pattern in (topic, kind + "/*", "*"):
            out.extend(self._subs.get(pattern, ()))
        return out

    def observed(self, topic: str) -> bool:
        hit = self._cache.get(topic)
        if hit is None:
            hit = self._cache[topic] = bool(self._listeners(topic))
        return hit

    def publish(self, topic: str, message: Mapping[str, Any]) -> None:
        if not self.observed(topic):
            return
        for listener in self._listeners(topic):
            try:
                listener(topic, message)
            except Exception:  # noqa: BLE001 - a listener's bug never reaches a device
                log.exception("listener of %s failed; unsubscribed", topic)
                for subs in self._subs.values():
                    if listener in subs:
                        subs.remove(listener)
                self._cache.clear()
