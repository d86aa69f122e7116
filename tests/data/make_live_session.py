"""Make ``live_session.mcap``: the live agent (``run_agent``) on a real Zenoh bus, every message recorded.

Run from the repository root: ``PYTHONPATH=. .venv/bin/python tests/data/make_live_session.py``.
The agent decides on ``synthetic_model(seed=3)`` with default ``AgentSettings(feeder_id="rural")`` the frames
that ``tests/agent/test_runtime.py`` builds (``live_frames``), one control step at a time (lockstep): its decisions
are the golden record the offline decision code must reproduce. Re-make it only when decisions change on
purpose, and say why in the commit.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "agent"))  # the frames of test_runtime

from test_runtime import FEEDER, LIVE_STEPS, live_frames  # noqa: E402

from agent.runtime import AgentSettings, run_agent  # noqa: E402
from benchmarks.synthetic import synthetic_model  # noqa: E402
from recordings.recorder import Recorder, RecorderConfig  # noqa: E402
from schemas import keys  # noqa: E402
from schemas.bus import BusConfig, codec_for, free_port, open_session, wait_for  # noqa: E402


def main(out: Path) -> int:
    model = synthetic_model(seed=3)
    settings = AgentSettings(feeder_id=FEEDER)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = BusConfig(mode="peer", connect=(endpoint,))
    stop = threading.Event()
    decided: list[bytes] = []
    statuses: list[bytes] = []
    with open_session(BusConfig(mode="router", listen=(endpoint,))), open_session(bus) as rec_session, \
            open_session(bus) as session:
        with Recorder(rec_session, RecorderConfig(out_path=str(out), keys=(f"cvvc/{FEEDER}/**",),
                                                  flush_period_s=0.1)):
            dec_sub = session.declare_subscriber(keys.agent_decision(FEEDER), lambda s: decided.append(b""))
            status_sub = session.declare_subscriber(keys.agent_status(FEEDER), lambda s: statuses.append(b""))
            agent = threading.Thread(target=run_agent, args=(model, settings, bus),
                                     kwargs={"stop": stop, "install_signals": False}, daemon=True)
            agent.start()
            try:
                if not wait_for(lambda: bool(statuses), 20.0):
                    raise SystemExit("the agent never published its status")
                pubs: dict[str, zenoh.Publisher] = {}
                for i in range(LIVE_STEPS):
                    for key, frame in live_frames(model, i):
                        if key not in pubs:
                            pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                        pubs[key].put(codec_for(type(frame)).encode(frame))
                    if i % 5 == 0 and not wait_for(lambda i=i: len(decided) == i // 5 + 1, 10.0):
                        raise SystemExit(f"no decision at step {i}")
            finally:
                stop.set()
                agent.join(15.0)
            dec_sub.undeclare()
            status_sub.undeclare()
    print(f"{out}: {len(decided)} decisions over {LIVE_STEPS} steps")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).with_name("live_session.mcap")))
