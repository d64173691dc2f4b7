"""Recordings of a run for Foxglove/Lichtblick: MCAP files and the live Foxglove WebSocket server.

:class:`~hilsim.record.recorder.Recorder` subscribes to the bridge's observer topics and logs
them with the Foxglove well-known schemas through the foxglove-sdk (``hilsim run
--record-mcap FILE.mcap``, ``--foxglove [PORT]``).
"""

from hilsim.record.recorder import Recorder

__all__ = ["Recorder"]
