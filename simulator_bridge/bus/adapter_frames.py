"""The frames the bridge waits for from field-protocol adapters (``cvvc run --pv-protocol sunspec`` /
``--field-protocol dnp3``), one step at a time.

A device behind an adapter (a PV plant behind SunSpec, a regulator control or bank behind DNP3) has no frame of the
bridge: its adapter reads the simulated device when the step's head frame arrives and publishes the frame. Before the
next step the bridge waits, bounded, until every such device's frame of the step arrived (:meth:`AdapterFrames.
frames_in`), so a lagging adapter never reads the next step's values and the agent gets the step's frames before the
next head frame. A device whose frame did not come in time is not waited for again until a frame of its own comes
(:meth:`AdapterFrames.missed`): an adapter whose link is down costs one wait, not one per step.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Literal

__all__ = ["AdapterFrames", "Protocol"]

Protocol = Literal["sunspec", "dnp3"]


class AdapterFrames:
    """The last frame time of each device behind an adapter, by ``(kind, device id)`` (kind ``pv``, ``vr``,
    ``cap``), and the steps that went without some of them.

    Parameters
    ----------
    devices : ``(kind, device id) -> protocol`` of every device behind an adapter.
    """

    def __init__(self, devices: Mapping[tuple[str, str], Protocol]) -> None:
        self.protocol = dict(devices)
        self.last_t_ns = {device: -1 for device in devices}
        self.misses: Counter[Protocol] = Counter()  # steps some device of that protocol missed
        self.lagging: set[tuple[str, str]] = set()  # devices not waited for until a frame of theirs comes

    def devices(self, kind: str) -> Iterable[str]:
        """The ids of the devices of ``kind`` behind an adapter."""
        return (d for k, d in self.protocol if k == kind)

    def on_frame(self, kind: str, device_id: str, t_ns: int) -> None:
        """A frame of ``device_id`` at ``t_ns`` [ns] arrived (frames of devices not behind an adapter are ignored)."""
        key = (kind, device_id)
        if key in self.last_t_ns and t_ns > self.last_t_ns[key]:
            self.last_t_ns[key] = int(t_ns)
            self.lagging.discard(key)

    def frames_in(self, t_ns: int) -> bool:
        """Whether the frame of the step at ``t_ns`` [ns] (or a later one) arrived from every device not lagging."""
        return all(t >= t_ns for key, t in self.last_t_ns.items() if key not in self.lagging)

    def missed(self, t_ns: int) -> list[str]:
        """The step at ``t_ns`` [ns] went without some devices' frames: count it once per protocol, and wait for
        those devices no more until a frame of theirs comes. Returns them as ``kind/id``.
        """
        late = [key for key, t in self.last_t_ns.items() if t < t_ns and key not in self.lagging]
        for protocol in {self.protocol[key] for key in late}:
            self.misses[protocol] += 1
        self.lagging.update(late)
        return [f"{k}/{d}" for k, d in late]
