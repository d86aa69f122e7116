"""Truth frames as arrays: the reader of ``sim/truth`` in every form it was written, and its JSON form.

The bridge publishes ``TruthPack`` as Protobuf (``cvvc.Truth``, ``schemas.truth_proto``; message encoding
``protobuf``), which Foxglove decodes from the schema in the recording. Recordings of earlier versions hold it as
MessagePack (``msgpack``, voltages as float32 byte planes: ``schemas.messages.pack_v_pu``), and older ones as
``TruthFrame`` (JSON text, ``json``). :func:`decode_truth` reads any of them into :class:`TruthArrays` (NumPy
arrays), by the MCAP channel's message encoding; :func:`truth_pack` gives the ``TruthPack`` of a compact one (the
replay of an older recording republishes it on today's wire); :func:`to_truth_frame` turns a pack into the JSON
``TruthFrame`` (``cvvc recordings export-json``: a copy of a recording with the truth as JSON, which Foxglove plots
for recordings whose truth is MessagePack).
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from schemas import messages as m
from schemas.errors import CvvcError
from schemas.truth_proto import decode_truth_proto

__all__ = ["TruthArrays", "TruthDecodeError", "decode_truth", "to_truth_frame", "truth_arrays", "truth_pack"]

_PACK = msgspec.msgpack.Decoder(m.TruthPack)
_FRAME = msgspec.json.Decoder(m.TruthFrame)


class TruthDecodeError(CvvcError, ValueError):
    """A ``sim/truth`` payload that is not a truth frame in the encoding its channel names."""


@dataclass(frozen=True)
class TruthArrays:
    """One truth frame as arrays.

    Attributes
    ----------
    t_ns : simulation time [ns since the UTC epoch]. seq : the bridge's truth sequence number.
    v_pu : every node's voltage [pu of its nominal line-to-neutral voltage], float64 (from float32 in a
        ``TruthPack``: within 6e-8 pu of the simulated value). v_min_pu, v_max_pu : the step's extremes [pu]
        (exact). node_names : the engine's node names (first frame only, else None). taps : regulator taps
        (device-map order). pv_q_kvar : each plant's Q [kvar]. cap_states : closed steps of each bank.
    """

    t_ns: int
    seq: int
    v_pu: np.ndarray
    v_min_pu: float
    v_max_pu: float
    node_names: tuple[str, ...] | None
    taps: np.ndarray
    pv_q_kvar: np.ndarray
    cap_states: np.ndarray


def truth_arrays(msg: m.TruthPack | m.TruthFrame) -> TruthArrays:
    """The arrays of a decoded truth message, compact or JSON (new arrays: nothing shares ``msg``'s memory)."""
    if isinstance(msg, m.TruthPack):
        v = m.unpack_v_pu(msg.v_pu_f32, msg.n_nodes)
    else:
        v = np.asarray(msg.v_pu, dtype=np.float64)
    return TruthArrays(t_ns=msg.t_ns, seq=msg.seq, v_pu=v, v_min_pu=msg.v_min_pu, v_max_pu=msg.v_max_pu,
                       node_names=None if msg.node_names is None else tuple(msg.node_names),
                       taps=np.asarray(msg.taps, dtype=np.int64), pv_q_kvar=np.asarray(msg.pv_q_kvar, dtype=float),
                       cap_states=np.asarray(msg.cap_states, dtype=np.int64))


def decode_truth(raw: bytes, message_encoding: str) -> TruthArrays:
    """A recorded or received ``sim/truth`` payload as arrays.

    Parameters
    ----------
    raw : the payload. message_encoding : the MCAP channel's: ``protobuf`` (``cvvc.Truth``, this version),
        ``msgpack`` (``TruthPack``, earlier recordings) or ``json`` (``TruthFrame``, recordings before those).

    Raises
    ------
    TruthDecodeError
        Another encoding, or a payload that does not decode (types, bounds, byte count).
    """
    if message_encoding == "json":
        try:
            return truth_arrays(_FRAME.decode(raw))
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as e:  # ValidationError is a DecodeError
            raise TruthDecodeError(f"not a truth frame (json): {e}") from e
    return truth_arrays(truth_pack(raw, message_encoding))


def truth_pack(raw: bytes, message_encoding: str) -> m.TruthPack:
    """The ``TruthPack`` of a compact truth payload: ``protobuf`` (this version) or ``msgpack`` (earlier ones).

    Raises
    ------
    TruthDecodeError
        Another encoding, or a payload that does not decode (types, bounds, byte count).
    """
    try:
        if message_encoding == "protobuf":
            return decode_truth_proto(raw)
        if message_encoding == "msgpack":
            return _PACK.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as e:  # ValidationError is a DecodeError
        raise TruthDecodeError(f"not a truth frame ({message_encoding}): {e}") from e
    raise TruthDecodeError(f"truth frames are protobuf (cvvc.Truth), msgpack (TruthPack) or json (TruthFrame), not "
                           f"{message_encoding!r}")


def to_truth_frame(msg: m.TruthPack) -> m.TruthFrame:
    """The JSON form of a compact truth frame (``v_pu`` as a list of the float32 values, widened)."""
    return m.TruthFrame(t_ns=msg.t_ns, seq=msg.seq, source=msg.source, feeder_id=msg.feeder_id,
                        v_pu=m.unpack_v_pu(msg.v_pu_f32, msg.n_nodes).tolist(), v_min_pu=msg.v_min_pu,
                        v_max_pu=msg.v_max_pu, node_names=msg.node_names, taps=msg.taps, pv_q_kvar=msg.pv_q_kvar,
                        cap_states=msg.cap_states)
