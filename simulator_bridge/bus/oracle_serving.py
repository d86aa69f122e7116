"""Serving the case-A oracle on the bus (``sim/oracle``), rate limited, from the bridge's stepping thread.

A Zenoh query is only decoded and enqueued on the bridge's inbox in the Zenoh thread (:class:`OracleQuery`);
the stepping thread answers it between steps (:meth:`OracleServer.answer`) with
:class:`~simulator_bridge.simulation.oracle.Oracle`'s reply, at most :data:`ORACLE_REPLIES_PER_STEP` per simulated step,
so a power flow never runs in a Zenoh thread and never concurrently with a step.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import Inbox, Received, codec_for
from schemas.errors import CvvcError
from simulator_bridge.simulation.oracle import Oracle

if TYPE_CHECKING:
    from simulator_bridge.bus.device_bank import BridgeCounters
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

__all__ = ["ORACLE_REPLIES_PER_STEP", "OracleQuery", "OracleServer"]

log = logging.getLogger("simulator_bridge.bus.bridge")  # the bridge's log lines, under the bridge's name

ORACLE_REPLIES_PER_STEP = 2
"""Case-A oracle replies the bridge gives per simulated step (the agent asks once per control step; one retry)."""


@dataclass(frozen=True)
class OracleQuery:
    """An oracle query waiting on the bridge's inbox for the stepping thread: the query and its decoded request."""

    query: zenoh.Query
    request: m.OracleRequest


class OracleServer:
    """The oracle's queryable and its answers (see the module docstring).

    Parameters
    ----------
    session : the bridge's Zenoh session. feeder_id : the feeder's id in the key space.
    engine : the stepping engine (the oracle compiles its twin now, not at the first query).
    qsts : the simulation (its next step's staged loads are taken back before an answer).
    inbox : the stepping thread's queue, where queries wait. counters : the run's counters (rejections, sequence
        numbers, log).
    """

    def __init__(self, session: zenoh.Session, feeder_id: str, engine: FeederEngine, qsts: Qsts, inbox: Inbox,
                 counters: BridgeCounters) -> None:
        self.oracle = Oracle(engine)
        self.fid, self.qsts, self.counters, self._inbox = feeder_id, qsts, counters, inbox
        self.replies = self.rejected = 0
        self._step_t_ns, self._step_replies = -1, 0
        self.queryable = session.declare_queryable(keys.sim_oracle(feeder_id), self._on_query, complete=True)

    def _on_query(self, query: zenoh.Query) -> None:
        """Decode the request and enqueue it for the stepping thread; never compute here."""
        inbox = self._inbox
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            request = (codec_for(m.OracleRequest).decode(raw) if raw
                       else m.OracleRequest(t_ns=0))
        except CvvcError as e:
            inbox.rejects.reject(keys.sim_oracle(self.fid), "oracle_bad_request", str(e))
            query.reply_err(f"bad OracleRequest: {e}".encode())
            query.drop()
            return
        try:
            inbox.queue.put_nowait(Received(str(query.key_expr), OracleQuery(query, request), time.time_ns(), raw))
        except Exception:  # queue.Full
            inbox.rejects.reject(keys.sim_oracle(self.fid), "oracle_busy", "queue full")
            query.reply_err(b"bridge busy: oracle queue full; retry after the next step")
            query.drop()

    def answer(self, item: OracleQuery, now_t_ns: int) -> None:
        """Answer one query at the step just simulated (``now_t_ns``), or refuse it past the rate limit."""
        q = item.query
        c = self.counters
        if self._step_t_ns != now_t_ns:
            self._step_t_ns, self._step_replies = now_t_ns, 0
        if self._step_replies >= ORACLE_REPLIES_PER_STEP:
            c.rejected["oracle_rate"] += 1
            q.reply_err(f"rate limited: at most {ORACLE_REPLIES_PER_STEP} oracle replies per simulated step; "
                        "ask again after the next step".encode())
            q.drop()
            return
        self._step_replies += 1
        try:
            self.qsts.unstage_loads()  # the oracle's flows are of the present state
            c.seqs["oracle"] += 1
            reply = self.oracle.reply(t_ns=now_t_ns, seq=c.seqs["oracle"], feeder_id=self.fid,
                                      include_sensitivities=item.request.include_sensitivities)
            q.reply(q.key_expr, codec_for(m.OracleReply).encode(reply), encoding=zenoh.Encoding.APPLICATION_JSON)
            self.replies += 1
        except CvvcError as e:
            self.rejected += 1
            c.rlog.warning("oracle_failed", "oracle query failed: %s", e)
            q.reply_err(f"oracle failed: {e}".encode())
        finally:
            q.drop()

    @staticmethod
    def refuse_at_shutdown(item: OracleQuery) -> None:
        """Answer a query still queued at shutdown with an error, so its getter does not wait for its timeout."""
        try:
            item.query.reply_err(b"bridge shutting down")
            item.query.drop()
        except Exception as e:  # the getter may be gone already
            log.info("could not answer an oracle query at shutdown: %s", e)

    def undeclare(self) -> None:
        """Withdraw the queryable (new queries are not answered any more)."""
        self.queryable.undeclare()

    def close(self) -> None:
        """Release the oracle's twin engine."""
        self.oracle.close()
